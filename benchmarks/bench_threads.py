"""Training-step wall time against torch's intra-op thread count (docs/PERFORMANCE.md, "Threads").

    python benchmarks/bench_threads.py SHARDS [--threads 1,2] [--rounds 2] [--workers 2]

Runs one-epoch ``fit``s of the ``cpu`` preset on SHARDS in one process, interleaving the thread counts
(1, 2, 1, 2, …) because timings on a shared machine drift, and prints the median per-step time of each
(from the run's losses.csv) with the load average. Render a small set first, e.g.
``risp-data render --env cube --n 96 --res 64 --spp 4 --shard-size 32 --out /tmp/cube``.
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import tempfile


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("shards")
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--reg", default="stochastic")
    args = ap.parse_args()

    from risp_train.config import make_config
    from risp_train.train import fit

    counts = [int(t) for t in args.threads.split(",")]
    steps: dict[int, list[float]] = {n: [] for n in counts}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for n in counts:
                out = os.path.join(tmp, f"r{r}-t{n}")
                fit(make_config(args.shards, out, preset="cpu", reg=args.reg, epochs=1, workers=args.workers,
                                threads=n), progress=False)
                with open(os.path.join(out, "losses.csv"), newline="") as f:
                    t = [float(row["seconds"]) for row in csv.DictReader(f)]
                steps[n] += [b - a for a, b in zip(t, t[1:])]
                print(f"round {r} threads {n}: median step {statistics.median(steps[n]):.3f} s "
                      f"(load {os.getloadavg()[0]:.1f})", flush=True)
    print(f"CPUs {len(os.sched_getaffinity(0))}, workers {args.workers}, reg {args.reg}, shards {args.shards}")
    for n in counts:
        print(f"threads {n}: median step {statistics.median(steps[n]):.3f} s over {len(steps[n])} steps")


if __name__ == "__main__":
    main()
