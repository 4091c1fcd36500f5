"""PNG figures — loss curves of a run, predicted vs true states, the ablation figure — drawn on matplotlib
figures without pyplot (risp_data.figures.subplots: the caller's backend is left alone)."""

from __future__ import annotations

import csv

from risp_data.figures import save_figure, subplots


def _save(fig, path: str, seed: int | None, what: str) -> None:
    save_figure(fig, path, seed=seed, what=what, tight=True)


def plot_losses(csv_path: str, png_path: str, history: list[dict] | None = None, reg: str = "none", *,
                seed: int | None) -> None:
    """State error and regularizer per step (log scale), held-out error per epoch when present.  ``reg``: the run's
    regularizer (what the right panel says when no step evaluated it).  A run of a few steps gets point markers
    (a line through one point is invisible)."""
    steps, err, values = [], [], []
    with open(csv_path, newline="") as f:
        for row in csv.DictReader(f):
            steps.append(int(row["step"]))
            err.append(float(row["error"]))
            values.append(float(row["reg"]))
    if not steps:
        return
    fig, ax = subplots(1, 2, figsize=(10, 3.6))
    marker = "o" if len(steps) <= 20 else None
    ax[0].plot(steps, err, lw=0.8, marker=marker, label="train state error ℓ (normalized L1)")
    val = [(h["step"], h["val_error"]) for h in (history or []) if h.get("val_error") is not None]
    if val:
        ax[0].plot(*zip(*val), "o-", label="held-out state error")
    ax[0].set_xlabel("step")
    ax[0].set_ylabel("state error (batch mean)")
    ax[0].set_yscale("log")
    ax[0].legend(fontsize=8)
    if any(r > 0 for r in values):
        # only the steps that evaluated it (r > 0): before γ's ramp the logged 0 is "not computed", which a log
        # axis would draw as a real value at its floor
        shown = [(st, r) for st, r in zip(steps, values) if r > 0]
        ax[1].plot(*zip(*shown), lw=0.8, marker="o" if len(shown) <= 20 else None, color="C2")
        ax[1].set_yscale("log")
        if len(steps) > 1:
            ax[1].set_xlim(min(steps), max(steps))
    else:
        text = ("no regularizer (--reg none)" if reg == "none" else
                f"--reg {reg}: not evaluated yet\n(γ = 0 before its ramp starts)")
        ax[1].text(0.5, 0.5, text, ha="center", va="center", transform=ax[1].transAxes)
    ax[1].set_xlabel("step")
    ax[1].set_ylabel("regularizer r (batch mean)")
    _save(fig, png_path, seed, "risp-train fit: loss curves")


def plot_predicted_vs_true(pred, true, names, png_path: str, title: str = "", units=None, *,
                           seed: int | None) -> None:
    """One scatter panel per state entry: prediction (y) against truth (x), with the diagonal y = x.  ``units``: one
    per entry ("m", "rad", "deg", …) for the panel titles; "deg" entries are given in radians and drawn in degrees,
    as the eval tables report attitude."""
    import numpy as np

    pred, true = np.asarray(pred, np.float64).copy(), np.asarray(true, np.float64).copy()
    units = list(units) if units is not None else [None] * len(names)
    for i, unit in enumerate(units):
        if unit == "deg":
            pred[:, i], true[:, i] = np.degrees(pred[:, i]), np.degrees(true[:, i])
    cols = min(len(names), 5)
    rows = -(-len(names) // cols)
    fig, axes = subplots(rows, cols, figsize=(2.6 * cols, 2.5 * rows), squeeze=False)
    for i, ax in enumerate(axes.ravel()):
        if i >= len(names):
            ax.axis("off")
            continue
        lo, hi = float(min(true[:, i].min(), pred[:, i].min())), float(max(true[:, i].max(), pred[:, i].max()))
        ax.plot([lo, hi], [lo, hi], color="0.6", lw=0.8)
        ax.scatter(true[:, i], pred[:, i], s=4, alpha=0.6)
        ax.set_title(names[i] + (f" [{'°' if units[i] == 'deg' else units[i]}]" if units[i] else ""), fontsize=9)
        ax.tick_params(labelsize=7)
    axes[0, 0].set_ylabel("predicted")
    axes[-1, 0].set_xlabel("true")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    _save(fig, png_path, seed, "risp-train eval: predicted vs true")


def plot_ablation(results: list[dict], png_path: str, metric: str, sets: list[str], *,
                  seed: int | None) -> None:
    """Held-out state error vs number of rendering configurations, one line per regularizer, one panel per set."""
    order = ["none", "surrogate", "exact", "stochastic"]
    regs = sorted({r["reg"] for r in results}, key=order.index)
    pools = sorted({r["pool"] for r in results}, key=lambda p: (p == "per-sample", int(p) if p.isdigit() else 0))
    labels = [("new per sample" if p == "per-sample" else f"{p} config" + ("" if p == "1" else "s")) for p in pools]
    fig, axes = subplots(1, len(sets), figsize=(5.2 * len(sets), 3.8), squeeze=False)
    for ax, s in zip(axes[0], sets):
        for k, reg in enumerate(regs):
            pts = [next((r[s] for r in results if r["reg"] == reg and r["pool"] == p), None) for p in pools]
            xs = [i + 0.06 * (k - len(regs) / 2) for i in range(len(pools))]
            ax.errorbar(xs, [p["mean"] if p else float("nan") for p in pts],
                        yerr=[p["std"] if p else float("nan") for p in pts], marker="o", capsize=3, label=reg)
        ax.set_xticks(range(len(pools)), labels)
        ax.set_title(f"evaluated on {s} shards")
        ax.set_ylabel(f"per-image state error ({metric})")
        ax.legend(fontsize=8)
    _save(fig, png_path, seed, "risp-train ablation")
