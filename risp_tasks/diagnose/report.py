"""report.md, report.json and the PNG plots of a diagnosis, written into a temporary folder that is renamed into place
whole (an earlier report in ``--out`` goes only once the new one is complete)."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import torch

from .adapter import measured_columns
from .fit import longest_even, make_segments, predict
from .residuals import one_step, unit_of
from risp_data.atomic import replace_folder, temp_folder, write_text_atomic
from risp_data.figures import save_figure

from ..strict_json import strict_json

PLOTS = {
    "residuals_time": "residuals_over_time.png",
    "residuals_regressors": "residuals_vs_regressors.png",
    "gain": "gain_overlay.png",
    "ranking": "ranking.png",
}
#: Every file a report folder holds (an --out holding only these is an earlier report, which a new one replaces), and
#: the files an operating system's file browser leaves in any folder it showed.
REPORT_FILES = frozenset({"report.json", "report.md", *PLOTS.values(), ".DS_Store", "Thumbs.db", "desktop.ini"})


def _named(path: Path, write) -> None:
    """Run ``write``; an OSError (disk full, permissions) is re-raised naming ``path``, not a temp name."""
    try:
        write()
    except OSError as e:
        raise OSError(e.errno, e.strerror or str(e), str(path)) from None


def _savefig(fig, path: Path, seed: int | None) -> None:
    def write():
        save_figure(fig, path, seed=seed, what=f"risp-task diagnose: {path.stem}", tight=True)

    _named(path, write)


# ------------------------------------------------------------------------------------------------
# plots
# ------------------------------------------------------------------------------------------------
MAX_PLOTTED_CHANNELS = 6
SMOOTH_SAMPLES = 11  # moving-average window of the smoothed residual curves


def _robust_ylim(ax, *arrays) -> None:
    """y limits from the 1st–99th percentiles (impact outliers must not flatten a few m/s² of friction)."""
    y = np.concatenate([np.ravel(a) for a in arrays if a is not None and np.size(a)])
    if y.size == 0:
        return
    lo, hi = np.percentile(y, [1, 99])
    pad = 0.15 * (hi - lo) + 1e-12
    ax.set_ylim(lo - pad, hi + pad)


def _smooth(y: np.ndarray, n: int = SMOOTH_SAMPLES) -> np.ndarray:
    """Centred moving average (shorter at the ends): measurement noise / Δ averages out, a bias stays."""
    if len(y) < 3:
        return y
    n = min(n, len(y) if len(y) % 2 else len(y) - 1)
    k = np.ones(n) / n
    num = np.convolve(y, k, mode="same")
    den = np.convolve(np.ones_like(y), k, mode="same")
    return num / den
MAX_OVERLAY_SAMPLES = 3000


def _top_channels(accel: np.ndarray) -> list[int]:
    """All channels of a rigid body (6); for many-channel states the 6 with the largest residual RMS."""
    if accel.shape[1] <= MAX_PLOTTED_CHANNELS:
        return list(range(accel.shape[1]))
    rms = np.sqrt(np.mean(accel**2, axis=0))
    return sorted(np.argsort(rms)[::-1][:MAX_PLOTTED_CHANNELS].tolist())


def plot_residuals_time(path: Path, os_base, os_ext, names: tuple[str, str], *, seed: int | None) -> None:
    from risp_data.figures import subplots

    chans = _top_channels(os_base.accel)
    A = len(chans)
    fig, axes = subplots(A, 1, figsize=(9, 1.6 * A + 0.6), sharex=True, squeeze=False)
    trajs = np.unique(os_base.traj)[:3]
    for row, c in enumerate(chans):
        ax = axes[row, 0]
        for j in trajs:
            m = os_base.traj == j
            ax.plot(os_base.t[m], os_base.accel[m, c], lw=0.5, color="C3", alpha=0.25)
            ax.plot(os_base.t[m], _smooth(os_base.accel[m, c]), lw=1.4, color="C3",
                    label=f"{names[0]} ({SMOOTH_SAMPLES}-sample mean)" if j == trajs[0] else None)
            if os_ext is not None:
                me = os_ext.traj == j
                ax.plot(os_ext.t[me], os_ext.accel[me, c], lw=0.5, color="C0", alpha=0.25)
                ax.plot(os_ext.t[me], _smooth(os_ext.accel[me, c]), lw=1.4, color="C0",
                        label=f"{names[1]} ({SMOOTH_SAMPLES}-sample mean)" if j == trajs[0] else None)
        ax.set_ylabel(os_base.accel_names[c], fontsize=8)
        ax.axhline(0, color="k", lw=0.5)
        _robust_ylim(ax, os_base.accel[:, c], None if os_ext is None else os_ext.accel[:, c])
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time [s] (held-out trajectories, up to 3)")
    fig.suptitle("one-step acceleration residuals a_meas − a_model (m/s², rad/s²); faint: raw, bold: moving mean; "
                 "y: 1st–99th percentile", fontsize=9)
    _savefig(fig, path, seed)


def plot_residuals_regressors(path: Path, os_base, *, seed: int | None) -> None:
    from risp_data.figures import subplots

    regs = [k for k in os_base.regressors if np.ptp(os_base.regressors[k]) > 0]
    chans = _top_channels(os_base.accel)
    A = len(chans)
    if not regs:
        regs = ["time [s]"]
    fig, axes = subplots(A, len(regs), figsize=(2.4 * len(regs) + 0.5, 1.6 * A + 0.6), squeeze=False)
    for row, c in enumerate(chans):
        for r, name in enumerate(regs):
            ax = axes[row, r]
            x = os_base.regressors.get(name, os_base.t)
            y = os_base.accel[:, c]
            ax.plot(x, y, ".", ms=1.5, alpha=0.35, color="C3")
            # binned means show the systematic part under the noise
            if np.ptp(x) > 0:
                edges = np.quantile(x, np.linspace(0, 1, 11))
                idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, 9)
                mids = [x[idx == b].mean() for b in range(10) if np.any(idx == b)]
                means = [y[idx == b].mean() for b in range(10) if np.any(idx == b)]
                ax.plot(mids, means, "-o", ms=2.5, color="k", lw=1)
            ax.axhline(0, color="k", lw=0.4)
            _robust_ylim(ax, y)
            xl = np.percentile(x, [0.5, 99.5])
            if xl[1] > xl[0]:
                ax.set_xlim(xl[0] - 0.05 * (xl[1] - xl[0]), xl[1] + 0.05 * (xl[1] - xl[0]))
            ax.tick_params(labelsize=6)
            if row == A - 1:
                ax.set_xlabel(name, fontsize=7)
            if r == 0:
                ax.set_ylabel(os_base.accel_names[c], fontsize=7)
    fig.suptitle("base-model one-step acceleration residuals vs candidate regressors (black: binned means; "
                 "axes: 1st–99th percentile)", fontsize=9)
    _savefig(fig, path, seed)


def plot_gain(path: Path, base_ev, ext_ev, held_trajs, horizon: int, *, seed: int | None) -> None:
    """Measured vs base vs extended open-loop rollouts, restarted from the measured state every H_r samples."""
    from risp_data.figures import subplots

    tr = max(held_trajs, key=lambda t: t.n)
    tr = tr.slice(0, min(tr.n, MAX_OVERLAY_SAMPLES), "")  # a long log: its first part is plenty to look at
    H = max(1, longest_even([tr], min(horizon, tr.n - 1)))
    series = {}
    for label, ev in (("base", base_ev), ("extended", ext_ev)):
        sim = ev.fit.model.sim
        seg = make_segments(sim, [tr], horizon=H, k=ev.k, stride=H, params=ev.fit.model.base)
        with torch.no_grad():
            pred = predict(sim, ev.fit.params, seg).numpy()  # (S, H+1, X)
        series[label] = (seg, pred, list(sim.state_names))
    seg, _, names = series["base"]
    meas_names = names
    chans = [n for n in ("x", "y", "z", "vx", "vy", "vz") if n in meas_names]
    if not chans:  # generalised coordinates: the ones that move most in this trajectory
        x = seg.meas.numpy()
        spread = x.reshape(-1, x.shape[-1]).std(0)
        chans = [meas_names[i] for i in sorted(np.argsort(spread)[::-1][:4].tolist())]
    fig, axes = subplots(len(chans), 1, figsize=(9, 1.5 * len(chans) + 0.6), sharex=True, squeeze=False)
    for c, name in enumerate(chans):
        ax = axes[c, 0]
        ax.plot(tr.t, measured_columns(tr)[name], color="k", lw=1.0, label="measured")
        for label, color in (("base", "C3"), ("extended", "C0")):
            sg, pred, nm = series[label]
            jj = nm.index(name)
            for s in range(sg.count):
                i0 = sg.start[s]
                tt = tr.t[i0 : i0 + H + 1]
                ax.plot(tt, pred[s, : len(tt), jj], color=color, lw=0.9, alpha=0.9,
                        label=(f"{label}: {ev_name(base_ev if label == 'base' else ext_ev)}" if s == 0 else None))
        ax.set_ylabel(name, fontsize=8)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel(f"time [s] — held-out trajectory {tr.name}; open-loop rollouts of {H} samples from measured states")
    _savefig(fig, path, seed)


def ev_name(ev) -> str:
    return ev.fit.model.name


def plot_ranking(path: Path, report: dict, *, seed: int | None) -> None:
    """The decision: held-out ΔBIC vs base (left) and the noise-floor ratio ρ (right), thresholds dashed."""
    from risp_data.figures import subplots

    rows = report["ranking"][::-1]
    if not rows:
        return
    th = report["thresholds"]
    names = [r["model"] for r in rows]
    dbic = [r["delta_bic"] for r in rows]
    rho = [r["noise_floor_ratio"] if r["noise_floor_ratio"] is not None else float("nan") for r in rows]
    sel = report.get("selected_model")
    fig, (a1, a2) = subplots(1, 2, figsize=(10, 0.35 * len(rows) + 1.4), sharey=True)
    beat = [d >= th["delta_bic_min"] and r["rss_reduction"] >= th["min_rss_reduction"] for d, r in zip(dbic, rows)]
    a1.barh(names, dbic, color=["C0" if b else "C7" for b in beat],
            edgecolor=["k" if n == sel else "none" for n in names])
    a1.axvline(th["delta_bic_min"], color="k", ls="--", lw=0.8, label=f"ΔBIC = {th['delta_bic_min']:g}")
    a1.set_xscale("symlog")
    a1.set_xlabel("held-out ΔBIC vs base (larger is better)")
    a1.legend(fontsize=7)
    a2.barh(names, rho, color=["C2" if v <= th["noise_floor_ratio_max"] else "C3" for v in rho],
            edgecolor=["k" if n == sel else "none" for n in names])
    a2.axvline(th["noise_floor_ratio_max"], color="k", ls="--", lw=0.8, label=f"ρ = {th['noise_floor_ratio_max']:g}")
    a2.axvline(1.0, color="k", lw=0.5)
    a2.set_xscale("log")
    a2.set_xlabel("held-out RSS / noise floor ρ (≈ 1: only noise left)")
    a2.legend(fontsize=7)
    fig.suptitle(f"cause: {report['cause']} (selected: {sel}, outlined); blue/green: passes, grey/red: fails", fontsize=9)
    _savefig(fig, path, seed)


# ------------------------------------------------------------------------------------------------
# markdown
# ------------------------------------------------------------------------------------------------
def _fmt(v, digits=4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.{digits}g}"


def markdown(report: dict) -> str:
    L = []
    L.append(f"# Diagnosis: {report['env']}\n")
    L.append(f"**Cause: `{report['cause']}`** — {report['reason']}.\n")
    if report["parameters"]:
        L.append("## Fitted parameters (model `" + report["selected_model"] + "`)\n")
        L.append("| parameter | value | ± 1σ (robust) | unit | note |\n|---|---|---|---|---|")
        for n, p in report["parameters"].items():
            note = f"**at its {p['at_bound']} limit {p['limit']:.4g}**: the fit is bounded, not determined" \
                if p.get("at_bound") else ""
            L.append(f"| {n} | {_fmt(p['value'])} | {_fmt(p['std'], 2)} | {p['unit']} | {note} |")
        L.append("")
    L.append("## Held-out error: base vs `" + report["compared_model"] + "`\n")
    L.append("| quantity | group | base | extended | gain |\n|---|---|---|---|---|")
    be, ee, g = report["base_error"], report["extended_error"], report["gain"]
    for key, label in (("one_step", "one-step error"), ("one_step_acceleration", "one-step acceleration residual"),
                       ("rollout", f"rollout error after {be['rollout_horizon_samples']} samples ({be['rollout_horizon_s']:.3g} s)")):
        for grp in be[key]:
            unit = unit_of(grp, report.get("env"))
            L.append(f"| {label} | {grp} [{unit}] | {_fmt(be[key][grp])} | {_fmt(ee[key][grp])} | {g[key][grp]:+.1%} |")
    L.append(f"| rollout error / noise σ (RMS over channels) | all | {_fmt(be['rollout_normalized'])} | "
             f"{_fmt(ee['rollout_normalized'])} | {g['rollout_normalized']:+.1%} |")
    L.append(f"| normalised held-out RSS | all | {_fmt(be['normalized_rss'])} | {_fmt(ee['normalized_rss'])} | {g['normalized_rss']:+.1%} |")
    L.append(f"| residual / noise floor ρ | all | {_fmt(be['noise_floor_ratio'], 3)} | {_fmt(ee['noise_floor_ratio'], 3)} | |\n")
    L.append("## Ranking (held-out BIC)\n")
    L.append("| model | k | held-out RSS | ΔBIC vs base | RSS reduction | ρ (noise floor ratio) |\n|---|---|---|---|---|---|")
    for r in report["ranking"]:
        L.append(f"| {r['model']} | {r['k']} | {_fmt(r['held_out_rss'])} | {r['delta_bic']:.1f} | {r['rss_reduction']:+.1%} | {_fmt(r['noise_floor_ratio'], 3)} |")
    t = report["thresholds"]
    L.append(f"\nThresholds: ΔBIC ≥ {t['delta_bic_min']:g} and RSS reduction ≥ {t['min_rss_reduction']:.0%} to beat a model; "
             f"ρ ≤ {t['noise_floor_ratio_max']:g} counts as explained (docs/diagnose.md).\n")
    deps = report.get("residual_dependence") or []
    if deps:
        L.append("## Remaining dependence of the selected model's held-out residual (docs/diagnose.md §6)\n")
        L.append("| regressor | channel | p (Bonferroni) | η² | significant |\n|---|---|---|---|---|")
        for d in deps[:5]:
            L.append(f"| {d['regressor']} | {d['channel']} | {d['p_value']:.2g} | {d['eta2']:.3f} | {'yes' if d['significant'] else 'no'} |")
        L.append("")
    if report["candidate_parameters"]:
        L.append("## Fitted parameters of every candidate\n")
        L.append("| model | parameter | value | ± 1σ |\n|---|---|---|---|")
        for m, ps in report["candidate_parameters"].items():
            for n, p in ps.items():
                L.append(f"| {m} | {n} | {_fmt(p['value'])} | {_fmt(p['std'], 2)} |")
        L.append("")
    s = report["split"]
    L.append("## Data and split\n")
    L.append(f"- {len(report['data']['files'])} file(s), {report['data']['samples']} samples, Δ = {report['data']['sample_interval_s']:.5g} s; sidecar: {report['data']['sidecar']}")
    L.append(f"- split by {s['mode']} (seed {s['seed']}): fitting {', '.join(s['fit'])}; held out {', '.join(s['held_out'])}")
    n = report["noise"]
    nm = report.get("noise_model") or {}
    L.append(f"- measurement noise (1σ), {nm.get('source', 'estimated')}: "
             + ", ".join(f"{k} {_fmt(v, 3)} {unit_of(k, report.get('env'))}" for k, v in n.items()))
    if nm.get("time_correlated") and not nm.get("declared_groups"):
        L.append("- **the estimated noise looks time-correlated** (lag-1 AR(1) fit of the smoothing residuals: "
                 + ", ".join(f"{k} {v:.2f}" for k, v in nm["lag1_correlation_estimate"].items())
                 + "): filtered data, or motion too fast for the 7-sample smoother. σ and ρ assume white noise and "
                   "are then only indicative; declare the sensor noise in the sidecar (`measurement_noise`, "
                   "`measurement_noise_correlation`) where it is known (docs/diagnose.md §4).")
    f = report["fit"]
    L.append(f"- multiple shooting: segments of {f['horizon_samples']} samples, {f['substeps_per_sample']} simulator step(s) of {f['sim_dt_s']:.4g} s per sample")
    L.append(f"- runtime {report['runtime_s']:.1f} s\n")
    L.append("## Plots\n")
    if not report.get("plots"):
        L.append("none (run with --no-plots)")
    for key in report.get("plots") or {}:
        L.append(f"![{key}]({PLOTS[key]})")
    return "\n".join(L) + "\n"


def replaced_whole(out: Path) -> bool:
    """Whether the report can replace ``out`` as a whole (a sibling folder renamed over it): not when ``out`` is a
    symlink (the rename would replace the link, not the folder it names), a mount point (a bind-mounted output
    folder cannot be renamed) or in a folder this user cannot write — then the files are written one by one inside
    it, each atomically."""
    if not os.path.lexists(out):
        return True
    if out.is_symlink() or os.path.ismount(out):
        return False
    return os.access(out.absolute().parent, os.W_OK | os.X_OK)


def write_report(report: dict, cfg, evaluated, base_ev, ext_ev, fit_trajs, held_trajs) -> None:
    """Write report.json, report.md and the plots into a temporary sibling of ``cfg.out`` and rename it into place
    (an earlier report there is replaced only once the new one is complete), so the folder always holds one
    report whole: a failed or interrupted write leaves the earlier one untouched.  Where the folder cannot be
    replaced (:func:`replaced_whole`), the files are written into it one by one instead."""
    out = Path(cfg.out)
    if not replaced_whole(out):
        if not cfg.plots:  # an earlier report's PNGs here would pass for this one's
            for fn in PLOTS.values():
                (out / fn).unlink(missing_ok=True)
        _write_files(out, out, report, cfg, base_ev, ext_ev, held_trajs)
        return
    parent = out.absolute().parent
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(temp_folder(parent))
    try:
        _write_files(tmp, out, report, cfg, base_ev, ext_ev, held_trajs)
        replace_folder(tmp, out)
    except OSError as e:  # name the report's own path, not the temporary folder's
        shutil.rmtree(tmp, ignore_errors=True)
        name = str(e.filename or out).replace(str(tmp), str(out))
        raise OSError(e.errno, e.strerror or str(e), name) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_files(tmp: Path, out: Path, report: dict, cfg, base_ev, ext_ev, held_trajs) -> None:
    if cfg.plots:
        cap = dict(max_samples=10 * cfg.max_segments, seed=cfg.seed)
        os_b = one_step(base_ev.fit.model.sim, base_ev.obs, base_ev.fit.params, held_trajs, base_ev.k, **cap)
        os_e = None
        if ext_ev is not base_ev:
            os_e = one_step(ext_ev.fit.model.sim, ext_ev.obs, ext_ev.fit.params, held_trajs, ext_ev.k, **cap)
        plot_residuals_time(tmp / PLOTS["residuals_time"], os_b, os_e, ("base", ext_ev.fit.model.name), seed=cfg.seed)
        plot_residuals_regressors(tmp / PLOTS["residuals_regressors"], os_b, seed=cfg.seed)
        plot_gain(tmp / PLOTS["gain"], base_ev, ext_ev, held_trajs, report["base_error"]["rollout_horizon_samples"],
                  seed=cfg.seed)
        plot_ranking(tmp / PLOTS["ranking"], report, seed=cfg.seed)
        report["plots"] = {k: str(out / v) for k, v in PLOTS.items()}  # where they will be once renamed
    text = json.dumps(strict_json(report), indent=2, allow_nan=False)
    _named(out / "report.json", lambda: write_text_atomic(tmp / "report.json", text))
    _named(out / "report.md", lambda: write_text_atomic(tmp / "report.md", markdown(report)))
