"""Where an image-loss estimation cell's time goes (docs/PERFORMANCE.md §Task optimisation).

Runs the `pixelwise` per-image state optimisation of risp-task table's estimation cells (risp_tasks.tables.cells
.optimise_states) on a few sampled states of one environment at the cpu preset's 64x64 and spp 8, once to warm the
kernel cache, then once under cProfile; prints the wall time per image-iteration and the top of the profile.

    PYTHONPATH=. python benchmarks/profile_estimation_cell.py [--env quadrotor] [--images 4] [--iterations 5]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time
from types import SimpleNamespace


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="quadrotor")
    ap.add_argument("--images", type=int, default=4)
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import numpy as np
    import torch

    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment
    from risp_tasks.tables.cells import optimise_states

    torch.set_num_threads(1)  # as every table cell (risp_tasks/tables/grid.py)
    env = get_environment(args.env)
    states = torch.tensor(env.sample_states(np.random.default_rng(args.seed), args.images + 1), dtype=torch.float32)
    with torch.no_grad():
        images = StateRenderer(args.env, resolution=64, spp=8)(states[:-1], seed=3)
    start = states[-1:].expand(args.images, -1)
    cfg = SimpleNamespace(resolution=64, spp=8, lr=3e-2, iterations=args.iterations, perceptual_weights=None)
    optimise_states(cfg, env, images, start, "pixelwise")  # warm-up: compiles and caches the kernels
    prof = cProfile.Profile()
    t = time.perf_counter()
    prof.enable()
    optimise_states(cfg, env, images, start, "pixelwise")
    prof.disable()
    wall = time.perf_counter() - t
    print(f"{args.env}: {wall:.2f} s, {wall / (args.images * args.iterations):.3f} s per image-iteration")
    pstats.Stats(prof).sort_stats("cumulative").print_stats(30)


if __name__ == "__main__":
    main()
