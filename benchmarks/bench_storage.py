"""Own-channel vs full Jacobian storage (issue 9): bytes on disk, write time and trainer-side decode time.

    python benchmarks/bench_storage.py                    # cube and hand, train and target, 32 samples each
    python benchmarks/bench_storage.py --envs cube --domains train --samples 8

Renders the samples once (real Mitsuba renders with their forward-mode J, 64×64, 16 spp), then writes the
same samples as one shard folder per layout — ``own-channel`` (the default of ``risp-data render``) and
``full`` (``--full-jacobian``) — in both formats, interleaved, ``--repeats`` times, and reads every sample
back through the readers the trainer uses (``decode_wds_sample`` on raw tar members, ``ZarrDataset``).
Checks that both layouts give back the same J bit for bit.  Prints medians and the load average.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

LAYOUTS = {"own-channel": True, "full": False}


def render_samples(env: str, domain: str, n: int, res: int, spp: int):
    from risp_data.envs import get_environment
    from risp_data.generate import RenderJob, make_renderer, render_sample

    job = RenderJob(env=env, n=n, out="", domain=domain, resolution=res, spp=spp, shard_size=n, seed=0)
    renderer = make_renderer(job)
    return [render_sample(renderer, get_environment(env), job, i) for i in range(n)]


def write(folder: str, env: str, domain: str, samples, res: int, spp: int, compact: bool, fmt: str) -> float:
    """Write ``samples`` as shard 0 of a fresh folder in format ``fmt``; returns the seconds of write_shard."""
    from risp_data.generate import RenderJob, new_manifest
    from risp_data.shards.manifest import save_manifest
    from risp_data.shards.writer import write_shard
    from risp_data.shards.zarr_store import create_store

    shutil.rmtree(folder, ignore_errors=True)
    os.makedirs(folder)
    job = RenderJob(env=env, n=len(samples), out=folder, domain=domain, formats=(fmt,), resolution=res, spp=spp,
                    shard_size=len(samples), seed=0, compact_jacobian=compact)
    m = new_manifest(job, samples[0].meta["variant"])
    save_manifest(folder, m)
    if fmt == "zarr":
        create_store(folder, m)
    t0 = time.perf_counter()
    m["shards"] = [write_shard(folder, (fmt,), 0, samples)]
    dt = time.perf_counter() - t0
    save_manifest(folder, m)
    return dt


def shard_bytes(folder: str) -> int:
    """Bytes of the shard files the manifest lists (tar, or the zarr shard files of every array)."""
    from risp_data.shards import load_manifest

    return sum(info["bytes"] for rec in load_manifest(folder)["shards"] for info in rec["files"].values())


def read(folder: str, fmt: str):
    """(seconds per sample to decode every sample as the trainer does, the decoded J stacks)."""
    import webdataset as wds

    from risp_data.shards import ZarrDataset, decode_wds_sample, wds_urls

    if fmt == "wds":
        raws = list(wds.WebDataset(wds_urls(folder), shardshuffle=False))  # tar reading outside the timing
        t0 = time.perf_counter()
        out = [decode_wds_sample(r)["jacobian"] for r in raws]
    else:
        ds = ZarrDataset(folder)
        t0 = time.perf_counter()
        out = [ds[i]["jacobian"] for i in range(len(ds))]
    return (time.perf_counter() - t0) / len(out), out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--envs", default="cube,hand")
    p.add_argument("--domains", default="train,target")
    p.add_argument("--samples", type=int, default=32)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--res", type=int, default=64)
    p.add_argument("--spp", type=int, default=16)
    a = p.parse_args()
    print(f"{os.cpu_count()} CPU cores, load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; "
          f"{a.samples} samples per env/domain, {a.res}x{a.res}, {a.spp} spp, {a.repeats} interleaved repeats")
    print(f"{'env/domain':<16} {'fmt':<5} {'layout':<12} {'KB/sample':>9} {'write ms/smp':>12} {'decode ms/smp':>13}")
    tmp = tempfile.mkdtemp(prefix="bench-storage-")
    try:
        for env in a.envs.split(","):
            for domain in a.domains.split(","):
                samples = render_samples(env, domain, a.samples, a.res, a.spp)
                for fmt in ("wds", "zarr"):
                    times = {k: ([], []) for k in LAYOUTS}
                    stacks, sizes = {}, {}
                    for _ in range(a.repeats):
                        for layout, compact in LAYOUTS.items():  # interleaved
                            folder = os.path.join(tmp, layout)
                            times[layout][0].append(write(folder, env, domain, samples, a.res, a.spp, compact, fmt))
                            dt, stacks[layout] = read(folder, fmt)
                            times[layout][1].append(dt)
                            sizes[layout] = shard_bytes(folder)
                    same = all(x.tobytes() == y.tobytes() == s.jacobian.tobytes()
                               for x, y, s in zip(stacks["own-channel"], stacks["full"], samples))
                    for layout in LAYOUTS:
                        w, r = (statistics.median(t) for t in times[layout])
                        print(f"{env + '/' + domain:<16} {fmt:<5} {layout:<12} {sizes[layout] / a.samples / 1e3:9.1f} "
                              f"{w / a.samples * 1e3:12.2f} {r * 1e3:13.2f}")
                    print(f"{'':<16} {fmt:<5} own-channel/full bytes {sizes['own-channel'] / sizes['full']:.3f}; "
                          f"J bit-identical to the rendered J in both layouts: {same}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"load average at the end {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
