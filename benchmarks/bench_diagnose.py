"""Benchmark: `risp-task diagnose` wall time for 10 trajectories × 300 samples per environment.

    python benchmarks/bench_diagnose.py            # quadrotor, cube, hand (rod with --envs rod)
    python benchmarks/bench_diagnose.py --quick    # 3 trajectories × 100 samples

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
    ap.add_argument("--trajectories", type=int, default=10)
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="3 trajectories × 100 samples")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.quick:
        args.trajectories, args.samples = 3, 100

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


if __name__ == "__main__":
    main()
