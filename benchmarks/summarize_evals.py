"""Aggregate `risp-train eval` results of several runs into the markdown tables of docs/RESULTS.md (issue 8).

    python benchmarks/summarize_evals.py RUN_DIR [RUN_DIR ...] [--sets target,val]

Each RUN_DIR is a `risp-train fit` run folder holding `config.json` and `eval-<set>.json` files written by
`risp-train eval MODEL SHARDS --out RUN_DIR/eval-<set>`.  Runs are grouped by (environment, regularizer,
γ, epochs); per group and evaluation set the table gives, for each state group (position m, attitude deg,
joints rad, sensors m) and the paper's L1, the mean over seeds of the per-run mean error ± the standard
deviation over seeds, the ratio to the `average` baseline, and the train→target gap (target − val) when
both sets are there.
"""

from __future__ import annotations

import argparse
import collections
import json
import os

import numpy as np


ORDER = ["position", "attitude", "joints", "sensors"]


def load_run(run: str, sets: list[str]) -> dict | None:
    cfg_path = os.path.join(run, "config.json")
    if not os.path.exists(cfg_path):
        return None
    with open(cfg_path) as f:
        meta = json.load(f)
    cfg = meta["config"]
    out = {"run": run, "env": meta.get("env") or json.load(open(os.path.join(run, f"eval-{sets[0]}.json")))["env"],
           "reg": cfg["reg"], "gamma": meta.get("gamma", cfg.get("gamma")), "epochs": cfg["epochs"],
           "seed": cfg["seed"], "evals": {}}
    for s in sets:
        p = os.path.join(run, f"eval-{s}.json")
        if os.path.exists(p):
            with open(p) as f:
                out["evals"][s] = json.load(f)
    return out


def group_table(runs: list[dict], sets: list[str]) -> str:
    groups = collections.defaultdict(list)
    for r in runs:
        groups[(r["env"], r["epochs"], r["reg"], r["gamma"])].append(r)
    lines = []
    for (env, epochs, reg, gamma), rs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][3] or 0)):
        for s in sets:
            evs = [r["evals"][s] for r in rs if s in r["evals"]]
            if not evs:
                continue
            names = sorted(evs[0]["groups"]["model"], key=ORDER.index) + ["l1"]
            cells = []
            for g in names:
                vals = np.array([e["results"]["model"]["mean"] if g == "l1" else e["groups"]["model"][g]["mean"]
                                 for e in evs])
                base = evs[0]["results"]["average"]["mean"] if g == "l1" else evs[0]["groups"]["average"][g]["mean"]
                fmt = "{:.1f}" if g == "attitude" else "{:.4f}"
                cells.append(f"{fmt.format(vals.mean())} ± {fmt.format(vals.std())} ({vals.mean() / base:.2f}×)")
            lines.append(f"| {env} | {epochs} | {reg} | {gamma:g} | {s} | {len(evs)} ({evs[0]['n']} img) | "
                         + " | ".join(f"{g}: {c}" for g, c in zip(names, cells)) + " |")
        both = [r for r in rs if all(x in r["evals"] for x in ("target", "val"))]
        if both:
            names = sorted(both[0]["evals"]["target"]["groups"]["model"], key=ORDER.index)
            gaps = [f"{g}: {np.mean([r['evals']['target']['groups']['model'][g]['mean'] - r['evals']['val']['groups']['model'][g]['mean'] for r in both]):+.4g}"
                    for g in names]
            lines.append(f"| {env} | {epochs} | {reg} | {gamma:g} | gap target − val | {len(both)} | " + ", ".join(gaps) + " |")
    head = "| env | epochs | reg | γ | eval set | seeds (images) | errors: mean over seeds ± std (ratio to `average`) |"
    return "\n".join([head, "|---|---:|---|---:|---|---|---|"] + lines)


def baselines(runs: list[dict], sets: list[str]) -> str:
    lines = ["| env | eval set | method | per-group error (mean ± std over images) | paper L1 |", "|---|---|---|---|---:|"]
    seen = set()
    for r in runs:
        for s, e in r["evals"].items():
            if (r["env"], s) in seen:
                continue
            seen.add((r["env"], s))
            for method in ("average", "random"):
                g = e["groups"][method]
                txt = ", ".join(f"{k} {v['mean']:.4g} ± {v['std']:.3g} {v['unit']}" for k, v in g.items())
                lines.append(f"| {r['env']} | {s} | {method} | {txt} | {e['results'][method]['mean']:.4f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--sets", default="target,val")
    args = ap.parse_args()
    sets = args.sets.split(",")
    runs = [r for r in (load_run(p, sets) for p in args.runs if not os.path.islink(p.rstrip("/"))) if r]
    print(group_table(runs, sets))
    print()
    print(baselines(runs, sets))


if __name__ == "__main__":
    main()
