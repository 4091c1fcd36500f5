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
           "control": "per-state L1 error (angles wrapped) between the reached and the pictured goal state, nominal "
                      "simulator, horizon = frames − 1"}


def aggregate(results: list[dict], env: str, method: str) -> dict:
    """{"mean", "std", "n"} over the repeats, or {"na": reason} when any repeat has no number."""
    rows = [r for r in results if r["env"] == env and r["method"] == method]
    na = [r["na"] for r in rows if "na" in r]
    if na:
        return {"na": na[0], "n_na": len(na), "n": len(rows)}
    values = np.array([r["value"] for r in rows], np.float64)
    return {"mean": float(values.mean()), "std": float(values.std()), "n": len(values), "values": values.tolist()}


def _fmt(entry: dict) -> str:
    if "na" in entry:
        return f"N/A ({entry['na']})"
    return f"{entry['mean']:.4g} ± {entry['std']:.2g}"


def build_report(cfg: TableConfig, results: list[dict]) -> dict:
    extractor = next((r["extractor"] for r in results if r.get("extractor")), None)
    table = {env: {m: aggregate(results, env, m) for m in cfg.methods} for env in cfg.envs}
    for env in cfg.envs:
        for m in cfg.methods:
            table[env][m]["paper"] = published(cfg.table, env, m)
    return {"table": cfg.table, "metric": METRICS[cfg.table], "config": cfg.to_dict(), "cells": table,
            "ours_regularizer": cfg.reg, "perceptual_extractor": extractor or (
                "vgg16-relu2_2" if cfg.perceptual_weights else "filterbank"),
            "paper_source": SOURCE, "seconds": float(sum(r.get("seconds", 0.0) for r in results)),
            "loadavg_max": max((r.get("loadavg", [0])[0] for r in results), default=0.0)}


def markdown(report: dict) -> str:
    cfg = report["config"]
    envs, methods = cfg["envs"], cfg["methods"]
    head = "| method | " + " | ".join(f"{e} (ours) | {e} (paper)" for e in envs) + " |"
    lines = [f"### {report['table']} ({cfg['preset']} preset{', quick' if cfg['quick'] else ''}, "
             f"{cfg['repeats']} repeats)", "",
             f"Metric: {report['metric']}; mean ± std over repeats (lower is better).", "",
             head, "|---|" + "---:|---:|" * len(envs)]
    for m in methods:
        row = []
        for e in envs:
            entry = report["cells"][e][m]
            paper = entry.get("paper")
            row += [_fmt(entry), "not found" if paper is None else f"{paper:.3g}†"]
        lines.append(f"| {m} | " + " | ".join(row) + " |")
    lines += ["", f"- `ours`: network trained with the `{report['ours_regularizer']}` regularizer "
                  f"(risp-train preset `{cfg['train_preset']}`); `ours-no-grad`: `--reg none`.",
              f"- `perceptual` feature extractor: `{report['perceptual_extractor']}` "
              "(risp_tasks/tables/methods.py).",
              f"- Sizes: {cfg['n_train']} training samples, {cfg['n_test']} test images per repeat, "
              f"{cfg['frames']} video frames, {cfg['iterations']} optimisation iterations, spp {cfg['spp']}, "
              f"{cfg['resolution']}×{cfg['resolution']}, seed {cfg['seed']}.",
              f"- Compute: {report['seconds']:.0f} s summed over cells (max 1-min load average "
              f"{report['loadavg_max']:.1f}: timings taken under load).",
              f"- † Paper numbers: {report['paper_source']}."]
    return "\n".join(lines)


def write_report(cfg: TableConfig, folder: str, results: list[dict]) -> dict:
    report = build_report(cfg, results)
    report["folder"] = folder
    write_text_atomic(os.path.join(folder, "table.json"), json.dumps(report, indent=1, sort_keys=True) + "\n")
    write_text_atomic(os.path.join(folder, "table.md"), markdown(report) + "\n")
    report["files"] = [os.path.join(folder, "table.md"), os.path.join(folder, "table.json")]
    return report
