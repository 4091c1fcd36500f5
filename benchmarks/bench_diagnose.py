"""Benchmark: `risp-task diagnose` wall time for 10 trajectories × 300 samples per environment.

    python benchmarks/bench_diagnose.py            # quadrotor, cube, hand (rod with --envs rod)
    python benchmarks/bench_diagnose.py --quick    # 3 trajectories × 100 samples
    python benchmarks/bench_diagnose.py --scale 12,50,100   # one long quadrotor log of ~N MB each

``--scale``: time and peak memory of `risp-task diagnose` (default options, no plots) on one quadrotor CSV
of about N MB each, in a fresh process per size (the CSV is a synthetic flight repeated end to end with
time running on; the jumps at the joins make a poor flight but a faithful load).

Synthetic data with one hidden effect (risp_tasks.diagnose.synth), the full pipeline without plots
(fit the base model, every single effect, pairs of the 3 best, held-out scoring and noise floor).
Prints the median over --repeats runs, the time per model fit and whether the hidden effect was named.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time

HIDDEN = {"quadrotor": "air_drag", "cube": "friction", "hand": "joint_damping", "rod": "rayleigh_damping"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--envs", default="quadrotor,cube,hand", help="comma-separated environments")
    ap.add_argument("--trajectories", type=int, default=None, help="trajectories per environment (10; --quick 3)")
    ap.add_argument("--samples", type=int, default=None, help="samples per trajectory (300; --quick 100)")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="3 trajectories × 100 samples")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scale", default=None, help="comma-separated CSV sizes in MB (quadrotor, one file each)")
    args = ap.parse_args()
    if args.scale:
        return scale([float(x) for x in args.scale.split(",")], args.seed)
    # --quick sets the sizes not given: an explicit --trajectories / --samples wins
    args.trajectories = args.trajectories or (3 if args.quick else 10)
    args.samples = args.samples or (100 if args.quick else 300)

    from risp_tasks.diagnose.run import DiagnoseConfig, diagnose
    from risp_tasks.diagnose.synth import SynthConfig, make_synthetic

    print(f"diagnose benchmark: {args.trajectories} trajectories × {args.samples} samples, repeats={args.repeats}")
    for env in [e.strip() for e in args.envs.split(",") if e.strip()]:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            truth = make_synthetic(SynthConfig(env=env, seed=args.seed, n_traj=args.trajectories, samples=args.samples,
                                               effect=HIDDEN[env]), tmp)
            t_synth = time.perf_counter() - t0
            times, report = [], None
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                report = diagnose(DiagnoseConfig(data=(tmp,), env=env, out=None, seed=args.seed, plots=False,
                                                 progress=False, horizon=5 if env == "rod" else 10))
                times.append(time.perf_counter() - t0)
            med = statistics.median(times)
            n_models = len(report["ranking"])
            print(f"{env:10s} median {med:7.1f} s  ({n_models} models, {med / n_models:5.1f} s/model; "
                  f"synthetic data {t_synth:5.1f} s)  hidden {truth['effect']} -> cause {report['cause']}")


def scale(sizes_mb: list[float], seed: int) -> None:
    import json
    import os
    import resource
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    import numpy as np

    from risp_tasks.diagnose.synth import SynthConfig, make_synthetic
    from risp_tasks.measured import read_csv_columns

    with tempfile.TemporaryDirectory() as tmp:
        make_synthetic(SynthConfig(env="quadrotor", seed=seed, n_traj=1, samples=600, effect="wind"), Path(tmp) / "src")
        src = Path(tmp) / "src" / "traj_000.csv"
        cols = read_csv_columns(src)
        block = src.read_text().split("\n", 1)[1]
        for mb in sizes_mb:
            reps = max(1, int(mb * 1e6 / len(block)))
            out = Path(tmp) / f"log_{mb:g}MB"
            out.mkdir()
            span = float(cols["t"][-1] - cols["t"][0]) + float(np.median(np.diff(cols["t"])))
            with open(out / "log.csv", "w") as fh:
                fh.write(",".join(cols) + "\n")
                data = np.stack(list(cols.values()), 1)
                for r in range(reps):
                    d = data.copy()
                    d[:, 0] += r * span
                    np.savetxt(fh, d, delimiter=",", fmt="%.9g")
            shutil.copy(src.with_suffix(".json"), out / "log.json")
            size = (out / "log.csv").stat().st_size / 1e6
            code = ("import json,sys,time,resource; from risp_tasks.diagnose.run import DiagnoseConfig, diagnose; "
                    f"t=time.perf_counter(); r=diagnose(DiagnoseConfig(data=('{out}',), env='quadrotor', out=None, seed={seed}, "
                    "plots=False, progress=False)); "
                    "print(json.dumps({'s': time.perf_counter()-t, 'rss_mb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss/1024, "
                    "'cause': r['cause'], 'samples': r['data']['samples']}))")
            env = {**os.environ, "OMP_NUM_THREADS": "1"}
            res = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                                            check=True).stdout.strip().splitlines()[-1])
            print(f"{size:6.1f} MB  {res['samples']:8d} samples  {res['s']:7.1f} s  peak RSS {res['rss_mb']:6.0f} MB  "
                  f"cause {res['cause']}  (load {os.getloadavg()[0]:.1f})")
            shutil.rmtree(out)


if __name__ == "__main__":
    main()
