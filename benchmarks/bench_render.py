"""Render cost per sample: primal only vs primal + K-dimensional Jacobian (issue 2 acceptance).

    python benchmarks/bench_render.py            # 64×64, 16 spp, every environment, 20 timed renders
    python benchmarks/bench_render.py --quick    # 5 timed renders

Prints, per environment, the median ms/sample of a primal-only render and of a render with the
Jacobian stack, their ratio, the ratio per ψ dimension ((with-J / primal − 1) / K), and the issue's
target (1 + 1.5·K)×.  Renders are interleaved (primal, with-J, primal, …) after warm-up so that load
changes on a shared machine hit both alike.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from risp_data.envs import ENV_NAMES, get_environment  # noqa: E402
from risp_data.psi import sample_rendering  # noqa: E402
from risp_data.render import Renderer  # noqa: E402


def bench_env(env: str, domain: str, resolution: int, spp: int, repeats: int, warmup: int, seed: int) -> dict:
    renderer = Renderer(env, domain, resolution=resolution, spp=spp)
    rng = np.random.default_rng(seed)
    states = get_environment(env).sample_states(rng, repeats + warmup)
    configs = [sample_rendering(env, domain, rng) for _ in range(repeats + warmup)]
    primal, full = [], []
    for i in range(repeats + warmup):
        t0 = time.perf_counter()
        renderer.render(states[i], configs[i], seed=i, jacobian=False)
        t1 = time.perf_counter()
        renderer.render(states[i], configs[i], seed=i, jacobian=True)
        t2 = time.perf_counter()
        if i >= warmup:
            primal.append(t1 - t0)
            full.append(t2 - t1)
    K = len(renderer.psi_names)
    p, f = statistics.median(primal) * 1e3, statistics.median(full) * 1e3
    return {"env": env, "K": K, "primal_ms": p, "jacobian_ms": f, "ratio": f / p,
            "per_dim": (f / p - 1) / K, "target": 1 + 1.5 * K}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="5 timed renders per environment instead of 20")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--domain", default="train")
    ap.add_argument("--env", action="append", choices=ENV_NAMES, help="environment(s); default: all")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    repeats, warmup = (5, 2) if args.quick else (20, 3)
    print(f"# {args.res}x{args.res}, {args.spp} spp, domain {args.domain}, median of {repeats} after {warmup} warm-up")
    print(f"{'env':10s} {'K':>2s} {'primal ms':>10s} {'with-J ms':>10s} {'ratio':>6s} {'per dim':>8s} {'target':>7s}")
    for env in args.env or ENV_NAMES:
        r = bench_env(env, args.domain, args.res, args.spp, repeats, warmup, args.seed)
        ok = "ok" if r["ratio"] <= r["target"] else "OVER"
        print(f"{r['env']:10s} {r['K']:2d} {r['primal_ms']:10.1f} {r['jacobian_ms']:10.1f} {r['ratio']:6.2f} "
              f"{r['per_dim']:8.2f} {r['target']:7.1f} {ok}")


if __name__ == "__main__":
    main()
