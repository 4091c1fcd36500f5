"""The report of a table: mean ± std over repeats per (environment, method), in the paper's layout (methods as
rows, environments as columns), with the paper's published number beside ours; markdown and JSON."""

from __future__ import annotations

import json
import os

import numpy as np

from risp_data.atomic import write_text_atomic

from .config import TableConfig
from .paper import SOURCE, published

METRICS = {"estimation": "per-image L1 state error (paper's metric; angles wrapped), target-domain images",
           "sysid": "absolute parameter error (quadrotor mass kg, cube log10 k_n, hand stiffness (mean of 5), "
                    "rod log10 E), target-domain reference video",
           "imitation": "state RMSE between reference and reproduced trajectory, target-domain reference video",
           "regularizers": "per-image L1 state error on target-domain images (same training set and budget per "
                           "regularizer; repeats = training seeds)",
           "sampling": "|argmin over a log10 E grid of the state loss − true log10 E| (rod, target-domain video)",
           "control": "per-state L1 error (angles wrapped) between the reached and the pictured goal state, nominal "
                      "simulator, horizon = frames − 1"}


def aggregate(results: list[dict], env: str, method: str, field: str = "value") -> dict:
    """{"mean", "std", "n"} of ``field`` over the repeats, or {"na": reason} when any repeat has no number."""
    rows = [r for r in results if r["env"] == env and r["method"] == method]
    na = [r["na"] for r in rows if "na" in r] or [f"no {field}" for r in rows if r.get(field) is None]
    if na:
        return {"na": na[0], "n_na": len(na), "n": len(rows)}
    values = np.array([r[field] for r in rows], np.float64)
    return {"mean": float(values.mean()), "std": float(values.std()), "n": len(values), "values": values.tolist()}


def group_cells(cfg: TableConfig, results: list[dict]) -> dict:
    """The estimation and regularizer tables per state group, in its unit (issue 8: position m, attitude °
    geodesic, hand joints rad, rod sensors m): {"<env> <group> [<unit>]": {row: mean ± std over repeats of the
    repeat's mean}}."""
    from risp_train.evaluate import STATE_GROUPS

    columns: dict = {}
    for env in cfg.envs:
        rows = [r for r in results if r["env"] == env]
        for group, (unit, _) in STATE_GROUPS[env].items():  # the evaluator's order (position before attitude)
            per_group = [{**r, "value": r.get("groups", {}).get(group, {}).get("mean")} for r in rows]
            columns[f"{env} {group} [{unit}]"] = {m: aggregate(per_group, env, m) for m in cfg.methods}
    return columns


def _fmt(entry: dict, notes: list[str]) -> str:
    """mean ± std, or "N/A [n]" with the reason as footnote n (one footnote per distinct reason)."""
    if "na" in entry:
        if entry["na"] not in notes:
            notes.append(entry["na"])
        return f"N/A [{notes.index(entry['na']) + 1}]"
    return f"{entry['mean']:.4g} ± {entry['std']:.2g}"


def build_report(cfg: TableConfig, results: list[dict]) -> dict:
    extractor = next((r["extractor"] for r in results if r.get("extractor")), None)
    table = {env: {m: aggregate(results, env, m) for m in cfg.methods} for env in cfg.envs}
    for env in cfg.envs:
        for m in cfg.methods:
            table[env][m]["paper"] = published(cfg.table, env, m)
    extra = {}
    if cfg.table in ("estimation", "regularizers"):
        extra["groups"] = group_cells(cfg, results)
    if cfg.table == "regularizers":
        extra["seconds_per_epoch"] = {env: {m: aggregate(results, env, m, "seconds_per_epoch") for m in cfg.methods}
                                      for env in cfg.envs}
    paper_source = {"regularizers": "the paper has no such table (its future work)",
                    "sampling": "the paper shows this ablation as a figure, without numbers"}.get(cfg.table, SOURCE)
    rows = {"sampling": "scheme", "regularizers": "regularizer"}.get(cfg.table, "method")
    return {**extra, "table": cfg.table, "metric": METRICS[cfg.table], "config": cfg.to_dict(), "cells": table,
            "rows": rows, "ours_regularizer": cfg.reg,
            "perceptual_extractor": extractor,  # None: no cell of this table ran `perceptual`
            "paper_source": paper_source, "seconds": float(sum(r.get("seconds", 0.0) for r in results)),
            "loadavg_max": max((r.get("loadavg", [0])[0] for r in results), default=0.0)}


def _rows(title: str, envs, methods, cells: dict, paper: bool, notes: list[str]) -> list[str]:
    head = f"| {title} | " + " | ".join(f"{e} (ours) | {e} (paper)" if paper else e for e in envs) + " |"
    lines = [head, "|---|" + ("---:|---:|" if paper else "---:|") * len(envs)]
    for m in methods:
        row = []
        for e in envs:
            row.append(_fmt(cells[e][m], notes))
            if paper:
                value = cells[e][m].get("paper")
                row.append("not found" if value is None else f"{value:.3g}†")
        lines.append(f"| {m} | " + " | ".join(row) + " |")
    return lines


def markdown(report: dict) -> str:
    cfg = report["config"]
    envs, methods = cfg["envs"], cfg["methods"]
    regs = "seconds_per_epoch" in report
    lines = [f"### {report['table']} ({cfg['preset']} preset{', quick' if cfg['quick'] else ''}, "
             f"{cfg['repeats']} repeats)", "",
             f"Metric: {report['metric']}; mean ± std over repeats (lower is better).", ""]
    notes: list[str] = []
    lines += _rows(report["rows"], envs, methods, report["cells"], paper=report["rows"] == "method", notes=notes)
    if report.get("groups"):
        lines += ["", "Per state group, in its unit (the mean error of a repeat's images; mean ± std over repeats):", ""]
        lines += _rows(report["rows"], list(report["groups"]), methods, report["groups"], paper=False, notes=notes)
    if regs:
        lines += ["", "Median wall time per training epoch with the regularizer on [s] "
                      "(mean ± std over repeats; under load, see below):", ""]
        lines += _rows("regularizer", envs, methods, report["seconds_per_epoch"], paper=False, notes=notes)
        lines += ["", f"- Networks: risp-train preset `{cfg['train_preset']}`, γ its per-environment default; "
                      "figure: regularizers.png."]
    elif report["rows"] == "scheme":
        lines += ["", f"- N: the `ours` network (`{report['ours_regularizer']}` regularizer); figure: sampling.png."]
    else:
        lines += ["", f"- `ours`: network trained with the `{report['ours_regularizer']}` regularizer "
                      f"(risp-train preset `{cfg['train_preset']}`), `render` loss ‖N(R(s)) − N(I)‖; `ours-no-grad`: `--reg none`; "
                      "`ours-state`: the `ours` network, `state` loss ‖s − N(I)‖ (no rendering).",
                  "- `perceptual` feature extractor: " + (f"`{report['perceptual_extractor']}` (risp_tasks/tasks/features.py)."
                                                          if report["perceptual_extractor"] else "not used in this table.")]
        if report["table"] in ("sysid", "imitation", "control"):
            lines += [f"- Residual of the network-space losses: `{cfg.get('residual', 'l2')}` (`render`, `state`, "
                      "`oracle`; `pixelwise` and `perceptual` are squared image/feature differences)."]
    from .grid import UNUSED_BY
    from .sampling import SAMPLING_FRAMES

    unused = set(UNUSED_BY.get(report["table"], ()))  # the sizes this table does not read are not its sizes
    sizes = [f"{cfg['n_train']} training samples"]
    if "n_test" not in unused:
        sizes.append(f"{cfg['n_test']} test images per repeat")
    if report["rows"] == "scheme":  # the sampling ablation's videos have their own fixed length
        sizes.append(f"{SAMPLING_FRAMES} video frames")
    elif "frames" not in unused:
        sizes.append(f"{cfg['frames']} video frames")
    if "iterations" not in unused:
        sizes.append(f"{cfg['iterations']} optimisation iterations")
    lines += [f"- Sizes: {', '.join(sizes)}, spp {cfg['spp']}, {cfg['resolution']}×{cfg['resolution']}, "
              f"seed {cfg['seed']}.",
              f"- Compute: {report['seconds']:.0f} s summed over cells (max 1-min load average "
              f"{report['loadavg_max']:.1f}: timings taken under load).",
              f"- † Paper numbers: {report['paper_source']}."]
    lines += [f"- [{i}] N/A: {reason}" for i, reason in enumerate(notes, 1)]
    return "\n".join(lines)


def write_report(cfg: TableConfig, folder: str, results: list[dict]) -> dict:
    report = build_report(cfg, results)
    report["folder"] = folder
    write_text_atomic(os.path.join(folder, "table.json"), json.dumps(report, indent=1, sort_keys=True) + "\n")
    write_text_atomic(os.path.join(folder, "table.md"), markdown(report) + "\n")
    if cfg.table == "sampling":
        from .sampling import plot_sampling

        plot_sampling(results, os.path.join(folder, "sampling.png"), seed=cfg.seed)
    if cfg.table == "regularizers":
        plot_regularizers(report, os.path.join(folder, "regularizers.png"), seed=cfg.seed)
    report["files"] = [os.path.join(folder, "table.md"), os.path.join(folder, "table.json")]
    return report


def plot_regularizers(report: dict, path: str, *, seed: int) -> None:
    """Target-domain error vs wall time per epoch, one panel per environment, one point per regularizer."""
    from risp_data.figures import subplots

    from risp_data.figures import save_figure

    envs = report["config"]["envs"]
    fig, axes = subplots(1, len(envs), figsize=(3.2 * len(envs), 3.0), squeeze=False)
    for ax, env in zip(axes[0], envs):
        for reg, err in report["cells"][env].items():
            sec = report["seconds_per_epoch"][env][reg]
            if "na" in err or "na" in sec:
                continue
            ax.errorbar(sec["mean"], err["mean"], xerr=sec["std"], yerr=err["std"], fmt="o", label=reg, capsize=3)
        ax.set(title=env, xlabel="s / epoch", ylabel="target-domain L1 error")
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, seed=seed, what="risp-task table --table regularizers")
