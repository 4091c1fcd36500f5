"""Benchmark: the per-frame numpy work of risp's flat-shading boundary term (risp_data/flat_projective.py), per
environment: the broad phase of ``intersection_segments`` (sweep and prune against all n(n-1)/2 box pairs) and
the whole function, which runs once per frame in every render-mode backward pass (issue 10's ≤ 3 s per iteration).

    python benchmarks/bench_edges.py                   # every env, its mid-range state, medians of 20
    python benchmarks/bench_edges.py --envs quadrotor --repeats 50
"""

from __future__ import annotations

import argparse

import numpy as np
from bench_tasks import _median_time  # run as a script, so benchmarks/ is on the path


def _median_ms(fn, repeats: int) -> float:
    return 1e3 * _median_time(fn, repeats)


def all_pairs(lo: np.ndarray, hi: np.ndarray):
    """The broad phase as it was: every pair tested."""
    i, j = np.triu_indices(len(lo), 1)
    ok = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    return i[ok], j[ok]


def bench_env(name: str, repeats: int) -> dict:
    import torch

    from risp_data.envs import get_environment
    from risp_data.flat_projective import intersection_segments, overlapping_boxes

    env = get_environment(name)
    mid = torch.tensor([(a + b) / 2 for a, b in zip(env.state_low, env.state_high)], dtype=torch.float64)
    meshes = [(m.vertices.detach().numpy(), np.asarray(m.faces)) for m in env.meshes(mid)]
    tri = np.concatenate([V[F] for V, F in meshes])
    lo, hi = tri.min(1), tri.max(1)
    a, b = all_pairs(lo, hi), overlapping_boxes(lo, hi)
    if not (np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])):  # (an assert would vanish under -O)
        raise SystemExit("sweep and prune disagrees with all pairs")
    Vs, Fs = zip(*meshes)
    return {"env": name, "triangles": len(tri), "overlapping pairs": len(a[0]),
            "segments": len(intersection_segments(Vs, Fs)[0]),
            "all pairs ms": _median_ms(lambda: all_pairs(lo, hi), repeats),
            "sweep ms": _median_ms(lambda: overlapping_boxes(lo, hi), repeats),
            "intersection_segments ms": _median_ms(lambda: intersection_segments(Vs, Fs), repeats)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", default="quadrotor,cube,hand,rod")
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    print(f"{'env':10s} {'triangles':>9s} {'pairs':>7s} {'segments':>8s} {'all pairs':>10s} {'sweep':>8s} {'whole':>8s}  (ms, medians)")
    for name in args.envs.split(","):
        r = bench_env(name, args.repeats)
        print(f"{r['env']:10s} {r['triangles']:9d} {r['overlapping pairs']:7d} {r['segments']:8d} "
              f"{r['all pairs ms']:10.1f} {r['sweep ms']:8.1f} {r['intersection_segments ms']:8.1f}")


if __name__ == "__main__":
    main()
