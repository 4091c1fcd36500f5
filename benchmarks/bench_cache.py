"""Training from memory vs streaming the shards: wall time of whole ``fit`` runs (docs/PERFORMANCE.md,
§Training data in memory).

    python benchmarks/bench_cache.py SHARDS [--epochs 2] [--rounds 2] [--reg stochastic] [--configs NAME,…]

Runs short ``fit``s of the ``cpu`` preset on SHARDS in one process, interleaving the configurations (a shared
machine's speed drifts, so every round runs each once):

    stream w1 t1   streamed webdataset, 1 DataLoader worker, 1 torch thread (the tables' and RESULTS' runs)
    stream w2 t1   streamed, risp-train's default of 2 workers (torch threads: the CPUs left, 1 here)
    memory t1      decoded once into memory (2 decoding workers), 1 torch thread
    memory t2      the same with `--threads 2` (for a training that has the 2-core machine to itself)

and prints, per configuration, the median over rounds of the whole run's wall time (normalization statistics,
decoding into memory where it applies, every step, checkpoints) and of the median step, with the load average.
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import tempfile
import time

CONFIGS = {  # name: (cache, workers, threads)
    "stream w1 t1": ("stream", 1, 1),
    "stream w2 t1": ("stream", 2, 1),
    "memory t1": ("memory", 2, 1),
    "memory t2": ("memory", 2, 2),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("shards")
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--reg", default="stochastic")
    ap.add_argument("--configs", default=",".join(CONFIGS), help="comma-separated names of CONFIGS")
    args = ap.parse_args()

    import torch

    from risp_train.config import make_config
    from risp_train.train import fit

    names = [n.strip() for n in args.configs.split(",")]
    wall: dict[str, list[float]] = {n: [] for n in names}
    step: dict[str, list[float]] = {n: [] for n in names}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for name in names:
                cache, workers, threads = CONFIGS[name]
                out = os.path.join(tmp, f"r{r}-{name.replace(' ', '-')}")
                cfg = make_config(args.shards, out, preset="cpu", reg=args.reg, epochs=args.epochs, workers=workers,
                                  threads=threads, cache=cache)
                t0 = time.perf_counter()
                fit(cfg, progress=False)
                wall[name].append(time.perf_counter() - t0)
                with open(os.path.join(out, "losses.csv"), newline="") as f:
                    t = [float(row["seconds"]) for row in csv.DictReader(f)]
                step[name].append(statistics.median(b - a for a, b in zip(t, t[1:])))
                print(f"round {r} {name:13s}: run {wall[name][-1]:7.1f} s, median step {step[name][-1] * 1e3:6.1f} ms "
                      f"({len(t)} steps; load {os.getloadavg()[0]:.1f})", flush=True)
    print(f"CPUs {len(os.sched_getaffinity(0))}, torch {torch.__version__}, reg {args.reg}, epochs {args.epochs}, "
          f"shards {args.shards}")
    base = statistics.median(wall[names[0]])
    print("| configuration | run [s] | × first | median step [ms] |\n|---|---:|---:|---:|")
    for n in names:
        w = statistics.median(wall[n])
        print(f"| {n} | {w:.1f} | {w / base:.2f} | {statistics.median(step[n]) * 1e3:.1f} |")


if __name__ == "__main__":
    main()
