"""Render cost per sample: primal vs primal + K = 8 Jacobian stack, fast vs legacy path (issue 9).

    python benchmarks/bench_render.py            # 64×64, 16 spp, every env × domain, 12 timed renders; job bench
    python benchmarks/bench_render.py --quick    # 4 timed renders per env × domain, smaller job bench
    python benchmarks/bench_render.py --no-job   # renderer only

Part 1 (renderer): per environment and domain, the median ms/sample of a primal-only render and of a
render with the Jacobian stack by the fast and the legacy path, interleaved (primal, fast, legacy,
primal, …) after warm-up, so load changes on a shared machine hit all three alike.  Prints with-J /
primal for both paths (issue 9 target: fast ≤ 4×).

Part 2 (job): samples/s of the real ``risp-data render`` command (2 workers, cube, train) with
``--jacobian-path fast`` and ``legacy``, alternated in the same run (fast, legacy, fast, legacy, …);
median rate each and their ratio (issue 9 target: ≥ 2.5×).  Each run renders into a fresh temp folder.
A run with n = 8 beside each gives the fixed start-up cost, so the rate without start-up (what a
10 000-sample job sees) is (n − 8) / (t_n − t_8); the 10 000-sample time is extrapolated from it.

The 1-, 5- and 15-minute load averages are printed before and after each part: on a shared machine
quote them beside the figures.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from risp_data.envs import ENV_NAMES, get_environment  # noqa: E402
from risp_data.psi import DOMAINS, sample_rendering  # noqa: E402
from risp_data.render import Renderer  # noqa: E402


def load() -> str:
    return "load average %.2f %.2f %.2f" % os.getloadavg()


def bench_env(env: str, domain: str, resolution: int, spp: int, repeats: int, warmup: int, seed: int) -> dict:
    fast = Renderer(env, domain, resolution=resolution, spp=spp, jacobian_path="fast")
    legacy = Renderer(env, domain, resolution=resolution, spp=spp, jacobian_path="legacy")
    rng = np.random.default_rng(seed)
    states = get_environment(env).sample_states(rng, repeats + warmup)
    configs = [sample_rendering(env, domain, rng) for _ in range(repeats + warmup)]
    times: dict[str, list[float]] = {"primal": [], "fast": [], "legacy": []}
    for i in range(repeats + warmup):
        runs = {"primal": lambda: fast.render(states[i], configs[i], seed=i, jacobian=False),
                "fast": lambda: fast.render(states[i], configs[i], seed=i),
                "legacy": lambda: legacy.render(states[i], configs[i], seed=i)}
        for name, run in runs.items():
            t0 = time.perf_counter()
            run()
            if i >= warmup:
                times[name].append(time.perf_counter() - t0)
    ms = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    return {"env": env, "domain": domain, **ms, "fast_ratio": ms["fast"] / ms["primal"],
            "legacy_ratio": ms["legacy"] / ms["primal"], "speedup": ms["legacy"] / ms["fast"]}


def run_job(path: str, n: int, workers: int, env: str, shard_size: int) -> float:
    """Wall seconds of one ``risp-data render`` run as the command reports them (n / its samples/s): from
    start to the last shard on disk (worker start-up, kernel cache loads, rendering, EXR/zarr writing)."""
    with tempfile.TemporaryDirectory(prefix="bench-render-") as tmp:
        cmd = [sys.executable, "-m", "risp_data", "render", "--env", env, "--n", str(n), "--out",
               os.path.join(tmp, "out"), "--workers", str(workers), "--shard-size", str(shard_size),
               "--jacobian-path", path, "--quiet"]
        env_vars = dict(os.environ, PYTHONPATH=ROOT, OMP_NUM_THREADS="1")
        out = subprocess.run(cmd, capture_output=True, text=True, env=env_vars, cwd=ROOT)
        if out.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed:\n{out.stderr}")
        return float(re.search(r"in ([\d.]+) s \(", out.stdout).group(1))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 timed renders per env × domain; 2 short job runs each")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--domain", action="append", choices=DOMAINS, help="domain(s); default: both")
    ap.add_argument("--env", action="append", choices=ENV_NAMES, help="environment(s); default: all")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-job", action="store_true", help="skip the risp-data render job comparison")
    ap.add_argument("--job-n", type=int, default=None, help="samples per job run (default 256; 64 with --quick)")
    ap.add_argument("--job-runs", type=int, default=None, help="runs per path (default 3; 2 with --quick)")
    args = ap.parse_args(argv)
    repeats, warmup = (4, 2) if args.quick else (12, 3)
    print(f"# machine: {os.cpu_count()} CPUs; {load()}")
    print(f"# renderer: {args.res}x{args.res}, {args.spp} spp, K = 8, median of {repeats} after {warmup} warm-up, "
          "interleaved primal / fast / legacy")
    print(f"{'env':10s} {'domain':6s} {'primal ms':>9s} {'fast ms':>8s} {'legacy ms':>9s} {'fast×':>6s} "
          f"{'legacy×':>7s} {'speedup':>7s}")
    for domain in args.domain or DOMAINS:
        for env in args.env or ENV_NAMES:
            r = bench_env(env, domain, args.res, args.spp, repeats, warmup, args.seed)
            print(f"{env:10s} {domain:6s} {r['primal']:9.1f} {r['fast']:8.1f} {r['legacy']:9.1f} "
                  f"{r['fast_ratio']:6.2f} {r['legacy_ratio']:7.2f} {r['speedup']:7.2f} "
                  f"{'ok' if r['fast_ratio'] <= 4 else 'OVER 4x'}", flush=True)
    print(f"# {load()}")
    if args.no_job:
        return
    n = args.job_n or (64 if args.quick else 256)
    runs = args.job_runs or (2 if args.quick else 3)
    small = 8
    if n <= 4 * small:  # the marginal rate divides by the time between the two sizes: they must differ well
        raise SystemExit(f"--job-n must be above {4 * small} (the start-up job renders {small}), got {n}")
    print(f"# job: risp-data render --env cube --n {n} --workers 2 --shard-size {n // 4} (64x64, 16 spp), and --n {small} "
          f"--shard-size {small // 2} for the fixed start-up cost; {runs} rounds, paths alternated; {load()}")
    secs: dict[tuple[str, int], list[float]] = {(p, m): [] for p in ("fast", "legacy") for m in (small, n)}
    for _ in range(runs):
        for path in ("fast", "legacy"):
            for m in (small, n):
                secs[path, m].append(run_job(path, m, 2, "cube", m // 4 if m == n else m // 2))
            print(f"  {path:6s} n={small}: {secs[path, small][-1]:6.1f} s   n={n}: {secs[path, n][-1]:6.1f} s "
                  f"= {n / secs[path, n][-1]:6.2f} samples/s   ({load()})", flush=True)
    med = {k: statistics.median(v) for k, v in secs.items()}
    rate = {p: n / med[p, n] for p in ("fast", "legacy")}
    marginal = {p: (n - small) / (med[p, n] - med[p, small]) for p in ("fast", "legacy")}
    print(f"job samples/s (as printed, n={n}): fast {rate['fast']:.2f}, legacy {rate['legacy']:.2f}, "
          f"ratio {rate['fast'] / rate['legacy']:.2f}  ({'ok' if rate['fast'] / rate['legacy'] >= 2.5 else 'below 2.5x'})")
    print(f"job samples/s without start-up ((n - {small}) / (t_n - t_{small})): fast {marginal['fast']:.2f}, "
          f"legacy {marginal['legacy']:.2f}, ratio {marginal['fast'] / marginal['legacy']:.2f}; "
          f"start-up ≈ {med['fast', small] - small / marginal['fast']:.1f} s (fast); "
          f"--n 10000 extrapolated: fast {10000 / marginal['fast'] / 60:.1f} min, legacy {10000 / marginal['legacy'] / 60:.1f} min")
    print(f"# {load()}")


if __name__ == "__main__":
    main()
