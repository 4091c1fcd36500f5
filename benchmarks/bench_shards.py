"""Shard-generation throughput: samples/s with 1 and 2 workers per environment (64×64, 16 spp),
including EXR/zarr encoding and writing, and the extrapolated time of
``risp-data render --env cube --n 10000 --res 64`` (target: ≤ 30 minutes on a 2-core CPU).

    python benchmarks/bench_shards.py            # 16 timed samples per worker and environment
    python benchmarks/bench_shards.py --quick    # 4 timed samples, cube only

Each worker builds its Renderer, renders and writes one warm-up shard (kernel compilation), waits at a
barrier, then renders and writes one timed shard; throughput = all timed samples / slowest worker.
Workers are spawned processes with cores // workers Dr.Jit threads each, as in ``risp-data render``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _job(env: str, out: str, m: int, res: int, spp: int):
    from risp_data.generate import RenderJob

    return RenderJob(env=env, n=1_000_000, out=out, resolution=res, spp=spp, shard_size=m, seed=0)


def _worker(env, rank, workers, m, res, spp, barrier, out):
    """Warm up, then time one shard of m samples (render + write both formats). Returns seconds."""
    import torch

    from risp_data.generate import make_renderer, prepare_folder, render_shard

    torch.set_num_threads(1)
    threads = max(1, (os.cpu_count() or 1) // workers)
    job = _job(env, out, m, res, spp)
    renderer = make_renderer(job, threads)
    if rank == 0:
        prepare_folder(job, renderer.variant)
    barrier.wait()
    render_shard(job, 2 * rank, renderer)  # warm-up shard: compiles kernels
    barrier.wait()
    t0, c0 = time.perf_counter(), time.process_time()
    render_shard(job, 2 * rank + 1, renderer)
    return time.perf_counter() - t0, time.process_time() - c0


def throughput(env: str, workers: int, m: int, res: int, spp: int) -> tuple[float, float]:
    """(samples/s by the wall clock, samples/s if every worker had its cores to itself: CPU-time based)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    ctx = mp.get_context("spawn")
    out = tempfile.mkdtemp(prefix=f"bench-shards-{env}-")
    try:
        with ctx.Manager() as manager:
            barrier = manager.Barrier(workers)
            with ProcessPoolExecutor(workers, mp_context=ctx) as ex:
                futs = [ex.submit(_worker, env, r, workers, m, res, spp, barrier, out) for r in range(workers)]
                times = [f.result() for f in futs]
    finally:
        shutil.rmtree(out, ignore_errors=True)
    wall = max(t for t, _ in times)
    cpu = max(c for _, c in times)  # all threads of the worker process
    threads = max(1, (os.cpu_count() or 1) // workers)
    return workers * m / wall, workers * m / (cpu / threads)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="4 timed samples per worker, cube only")
    p.add_argument("--samples", type=int, default=None, help="timed samples per worker (default 16, quick 4)")
    p.add_argument("--res", type=int, default=64)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--envs", default=None, help="comma-separated (default: all four; quick: cube)")
    a = p.parse_args()
    m = a.samples or (4 if a.quick else 16)
    envs = a.envs.split(",") if a.envs else (["cube"] if a.quick else ["quadrotor", "cube", "hand", "rod"])
    print(f"{os.cpu_count()} CPU cores (load average {os.getloadavg()[0]:.1f}); {a.res}x{a.res}, {a.spp} spp, "
          f"Jacobian on, both formats; {m} timed samples/worker")
    print("samples/s by the wall clock; in brackets the idle-machine estimate from CPU time (for a shared machine)")
    print(f"{'env':<10} {'1 worker':>20} {'2 workers':>20} {'ratio':>6}")
    rates, idle = {}, {}
    for env in envs:
        r1, i1 = throughput(env, 1, m, a.res, a.spp)
        r2, i2 = throughput(env, 2, m, a.res, a.spp)
        rates[env], idle[env] = max(r1, r2), i2
        print(f"{env:<10} {r1:7.2f} ({i1:6.2f}) smp/s {r2:7.2f} ({i2:6.2f}) smp/s {r2 / r1:6.2f}")
    if "cube" in rates:
        minutes = 10000 / rates["cube"] / 60
        print(f"extrapolated: risp-data render --env cube --n 10000 --res {a.res} (spp {a.spp}) ≈ {minutes:.1f} min "
              f"at {rates['cube']:.2f} samples/s measured, ≈ {10000 / idle['cube'] / 60:.1f} min on an idle machine "
              f"(2 workers, CPU-time estimate); + ~10 s start-up; target ≤ 30 min")


if __name__ == "__main__":
    main()
