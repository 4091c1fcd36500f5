"""PNG figures (matplotlib, Agg backend): the loss curves of a run and the ablation figure."""

from __future__ import annotations

import csv
import os


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str) -> None:
    tmp = path + ".tmp.png"
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    os.replace(tmp, path)


def plot_losses(csv_path: str, png_path: str, history: list[dict] | None = None) -> None:
    """State error and regularizer per step (log scale), held-out error per epoch when present."""
    steps, err, reg = [], [], []
    with open(csv_path, newline="") as f:
        for row in csv.DictReader(f):
            steps.append(int(row["step"]))
            err.append(float(row["error"]))
            reg.append(float(row["reg"]))
    if not steps:
        return
    plt = _pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ax[0].plot(steps, err, lw=0.8, label="train state error ℓ (normalized L1)")
    val = [(h["step"], h["val_error"]) for h in (history or []) if h.get("val_error") is not None]
    if val:
        ax[0].plot(*zip(*val), "o-", label="held-out state error")
    ax[0].set_xlabel("step")
    ax[0].set_yscale("log")
    ax[0].legend(fontsize=8)
    ax[1].plot(steps, [max(r, 1e-12) for r in reg], lw=0.8, color="C2")
    ax[1].set_xlabel("step")
    ax[1].set_ylabel("regularizer r (batch mean)")
    ax[1].set_yscale("log")
    _save(fig, png_path)
    plt.close(fig)


def plot_ablation(results: list[dict], png_path: str, metric: str) -> None:
    """Held-out state error vs number of rendering configurations, one line per regularizer."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    regs = sorted({r["reg"] for r in results}, key=["none", "surrogate", "exact", "stochastic"].index)
    pools = sorted({r["pool"] for r in results}, key=lambda p: (p == "per-sample", int(p) if p.isdigit() else 0))
    for reg in regs:
        ys = [next((r["mean"] for r in results if r["reg"] == reg and r["pool"] == p), float("nan")) for p in pools]
        es = [next((r["std"] for r in results if r["reg"] == reg and r["pool"] == p), float("nan")) for p in pools]
        ax.errorbar(range(len(pools)), ys, yerr=es, marker="o", capsize=3, label=reg)
    ax.set_xticks(range(len(pools)), [f"{p} config" + ("s" if p != "1" else "") if p != "per-sample"
                                      else "new per sample" for p in pools])
    ax.set_ylabel(f"state error on unseen ψ ({metric})")
    ax.legend(fontsize=8)
    _save(fig, png_path)
    plt.close(fig)
