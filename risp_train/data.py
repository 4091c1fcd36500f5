"""Streaming training data: webdataset tars (or the zarr store) → batches of raw images, J, states.

Nothing is loaded into memory beyond a shuffle buffer.  Webdataset shards are shuffled per epoch
(a permutation seeded by (seed, epoch)), split by node (``wds.split_by_node``: rank r takes shards
r, r+W, …) and by DataLoader worker (``wds.split_by_worker``), read as tar streams, shuffled through a
bounded buffer seeded by (seed, epoch, rank, worker) and decoded by ``risp_data.shards.decode_wds_sample``
in the worker processes.  The zarr store is read map-style: a permutation of sample indices seeded by
(seed, epoch), split by rank, batched, fetched by the workers.

Every rank must take the same number of optimizer steps per epoch (gradients are all-reduced), so the
number of steps of an epoch is computed up front from the manifest's per-shard counts
(:func:`steps_per_epoch`) and each rank stops after exactly that many full batches.  The data position
of a run is therefore (epoch, batch index within the epoch); a resumed run re-creates the same stream
and skips the batches already seen.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np
import torch

from risp_data.errors import RispError

FORMATS = ("auto", "wds", "zarr")


@dataclass(frozen=True)
class ShardSet:
    """A shard folder as training sees it: identity from the manifest and the complete shards."""

    folder: str
    manifest: dict
    format: str  # "wds" | "zarr"
    urls: tuple[str, ...]  # tar paths (wds) or ("",)*n (zarr); aligned with counts
    counts: tuple[int, ...]  # samples per complete shard
    starts: tuple[int, ...]  # first global sample index per shard

    @property
    def env(self) -> str:
        return str(self.manifest["env"])

    @property
    def resolution(self) -> int:
        return int(self.manifest["resolution"])

    @property
    def psi_names(self) -> tuple[str, ...]:
        return tuple(self.manifest["psi"]["names"])

    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(self.manifest["state_names"])

    @property
    def has_jacobian(self) -> bool:
        return bool(self.manifest.get("jacobian", False))

    @property
    def num_samples(self) -> int:
        return int(sum(self.counts))


def manifest_hash(manifest: dict) -> str:
    """sha256 of what the samples are: identity fields, ψ/state names and every shard file's sha256."""
    ident = {k: manifest.get(k) for k in
             ("env", "domain", "resolution", "spp", "variant", "jacobian", "n", "shard_size", "seed")}
    ident["psi"] = manifest.get("psi")
    ident["state_names"] = manifest.get("state_names")
    ident["files"] = sorted(
        (rel, info.get("sha256")) for rec in manifest.get("shards", []) for rel, info in rec.get("files", {}).items()
    )
    return hashlib.sha256(json.dumps(ident, sort_keys=True, default=str).encode()).hexdigest()


def open_shards(folder: str, fmt: str = "auto") -> ShardSet:
    """Read the manifest of ``folder`` and list its complete shards; RispError on anything unusable."""
    from risp_data.shards import load_manifest, wds_urls

    if fmt not in FORMATS:
        raise RispError(f"unknown --format {fmt!r}; choose one of: {', '.join(FORMATS)}")
    m = load_manifest(folder)
    formats = list(m.get("formats", []))
    if fmt == "auto":
        fmt = "wds" if "wds" in formats else "zarr" if "zarr" in formats else ""
    if fmt not in formats:
        raise RispError(f"shard folder {folder} holds no {fmt or 'readable'} shards (formats: {', '.join(formats)})")
    records = sorted(m["shards"], key=lambda r: r["index"])
    if not records:
        raise RispError(f"shard folder {folder} has no complete shards (empty shard list)")
    counts = tuple(int(r["stop"]) - int(r["start"]) for r in records)
    starts = tuple(int(r["start"]) for r in records)
    if fmt == "wds":
        urls = tuple(wds_urls(folder))  # checks existence and sizes
        if len(urls) != len(records):
            raise RispError(f"shard folder {folder}: manifest lists {len(records)} shards but {len(urls)} tar files")
    else:
        urls = tuple("" for _ in records)
    return ShardSet(folder=folder, manifest=m, format=fmt, urls=urls, counts=counts, starts=starts)


def check_environment(shards: ShardSet, env) -> None:
    """The shards' state vector must be the environment's (same names, same dimension)."""
    if tuple(shards.state_names) != tuple(env.state_names):
        raise RispError(
            f"shard folder {shards.folder}: state dimension/names {list(shards.state_names)} do not match "
            f"environment {env.name!r} ({list(env.state_names)})"
        )


def sample_counts(shards: ShardSet) -> dict:
    """What a run trains on, for its config: samples and shards read vs what the folder's job renders."""
    m = shards.manifest
    return {"used": shards.num_samples, "rendered_n": int(m["n"]), "shards": len(shards.counts),
            "num_shards": int(m["num_shards"])}


def check_complete(shards: ShardSet, allow_incomplete: bool) -> None:
    """An unfinished render folder is an error (training on a fraction of the data by accident) unless the
    user says ``--allow-incomplete``."""
    c = sample_counts(shards)
    if c["used"] < c["rendered_n"] and not allow_incomplete:
        raise RispError(f"shard folder {shards.folder} is incomplete: {c['used']} of {c['rendered_n']} samples "
                        f"({c['shards']} of {c['num_shards']} shards); finish it by rerunning its risp-data render "
                        "command, or pass --allow-incomplete to train on what is there")


# ----------------------------------------------------------------------------------------- planning


def epoch_shard_order(n_shards: int, seed: int, epoch: int) -> np.ndarray:
    """The permutation of shards used in ``epoch`` (identical on every rank)."""
    return np.random.default_rng(np.random.SeedSequence([seed, epoch, 0x5EED])).permutation(n_shards)


def effective_workers(n_shards: int, world_size: int, workers: int) -> int:
    """Each (rank, worker) needs at least one shard: cap the worker count at the shards per rank."""
    per_rank = n_shards // world_size
    if per_rank < 1:
        raise RispError(
            f"{n_shards} shard(s) cannot feed {world_size} processes: each rank needs at least one shard"
        )
    return max(0, min(workers, per_rank))


def map_style_steps(n: int, batch_size: int, world_size: int) -> int:
    """Full batches per rank and epoch of a map-style source of n samples (zarr, memory): ⌊⌊N / W⌋ / B⌋."""
    return (n // world_size) // batch_size


def steps_per_epoch(shards: ShardSet, seed: int, epoch: int, batch_size: int, world_size: int, workers: int) -> int:
    """Full batches every rank can produce in ``epoch`` (the minimum over ranks).

    Worker w of rank r reads shards order[r::W][w::nw] and yields ⌊n_rw / B⌋ full batches (drop_last).
    For zarr, each rank gets ⌊N / W⌋ samples, i.e. ⌊⌊N/W⌋ / B⌋ batches.
    """
    if shards.format == "zarr":
        return map_style_steps(shards.num_samples, batch_size, world_size)
    order = epoch_shard_order(len(shards.counts), seed, epoch)
    counts = np.asarray(shards.counts)[order]
    nw = max(1, effective_workers(len(counts), world_size, workers))
    per_rank = []
    for r in range(world_size):
        mine = counts[r::world_size]
        per_rank.append(sum(int(mine[w::nw].sum()) // batch_size for w in range(nw)))
    return min(per_rank)


# ------------------------------------------------------------------------------------------ streams


def _shuffle_buffer(src: Iterator[dict], size: int, seed_words: list[int]) -> Iterator[dict]:
    """Bounded-memory shuffle: keep ``size`` raw samples, emit a random one per new arrival."""
    rng = np.random.default_rng(np.random.SeedSequence(seed_words))
    buf: list[dict] = []
    for sample in src:
        if len(buf) < size:
            buf.append(sample)
            continue
        i = int(rng.integers(len(buf)))
        buf[i], sample = sample, buf[i]
        yield sample
    while buf:
        yield buf.pop(int(rng.integers(len(buf))))


def _decoder(need_jacobian: bool, resolution: int | None = None):
    from risp_data.shards import decode_wds_sample

    def decode(raw: dict) -> dict:
        if need_jacobian and "jacobian.exr" not in raw:
            raise RispError(f"webdataset sample {raw.get('__key__')} in {raw.get('__url__')} has no jacobian.exr")
        # checksums every member either way; an image of another size is refused before it is decoded
        d = decode_wds_sample(raw, jacobian=need_jacobian, resolution=resolution)
        d["url"] = raw.get("__url__", "")
        return d

    return decode


class WdsStream(torch.utils.data.IterableDataset):
    """One epoch of decoded samples for this rank, split over DataLoader workers (see the module doc)."""

    def __init__(self, urls: tuple[str, ...], seed: int, epoch: int, shuffle_buffer: int, need_jacobian: bool,
                 rank: int, shuffle: bool = True, split: bool = True, split_nodes: bool = True,
                 resolution: int | None = None, world_size: int = 1):
        super().__init__()
        self.resolution = resolution  # the manifest's: an image of another size is refused before decoding
        self.urls, self.seed, self.epoch = urls, seed, epoch
        self.shuffle_buffer, self.need_jacobian, self.rank, self.shuffle = shuffle_buffer, need_jacobian, rank, shuffle
        self.split = split  # False: every sample of every shard, in order (statistics, evaluation)
        self.split_nodes = split_nodes  # False: split over DataLoader workers only (each rank reads every shard)
        self.world_size = world_size  # rank r reads the epoch's shards r, r + W, … (as steps_per_epoch plans)

    def __iter__(self) -> Iterator[dict]:
        import webdataset as wds

        from risp_data.shards.wds import raise_with_url, shard_check_for_urls

        urls = list(self.urls)
        if self.shuffle:
            urls = [urls[i] for i in epoch_shard_order(len(urls), self.seed, self.epoch)]
        info = torch.utils.data.get_worker_info()
        worker = 0 if info is None else info.id
        stages: list[Any] = [wds.SimpleShardList(urls)]
        if self.split:
            # the rank's shards from its own rank and world size, not wds.split_by_node's reading of the process
            # group or the environment: the split the step plan assumes, whoever builds the stream
            by_rank = lambda src: itertools.islice(src, self.rank, None, self.world_size)  # noqa: E731
            stages += [by_rank, wds.split_by_worker] if self.split_nodes else [wds.split_by_worker]
        # tars → raw samples, each shard's samples checked against its manifest record (count, range, env)
        stages.append(shard_check_for_urls(list(self.urls), handler=raise_with_url).samples)
        if self.shuffle and self.shuffle_buffer > 1:
            words = [self.seed, self.epoch, self.rank, worker, 0xB0F]
            stages.append(lambda src: _shuffle_buffer(src, self.shuffle_buffer, words))
        stages.append(wds.map(_decoder(self.need_jacobian, self.resolution), handler=raise_with_url))
        return iter(wds.DataPipeline(*stages))


class ZarrSamples(torch.utils.data.Dataset):
    """Map-style view of the zarr store (opened lazily in each worker)."""

    def __init__(self, folder: str, need_jacobian: bool):
        self.folder, self.need_jacobian = folder, need_jacobian
        self._ds = None

    def _open(self):
        if self._ds is None:
            from risp_data.shards import ZarrDataset

            self._ds = ZarrDataset(self.folder)
        return self._ds

    def __len__(self) -> int:
        return len(self._open())

    def __getitem__(self, i: int) -> dict:
        d = dict(self._open()[i])
        d["url"] = self.folder
        if not self.need_jacobian:
            d["jacobian"] = None
        return d


def zarr_batches(n: int, seed: int, epoch: int, batch_size: int, rank: int, world_size: int) -> list[list[int]]:
    """This rank's batches of sample positions for ``epoch`` (full batches only)."""
    order = np.random.default_rng(np.random.SeedSequence([seed, epoch, 0x5EED])).permutation(n)
    mine = order[rank: (n // world_size) * world_size: world_size]
    nb = len(mine) // batch_size
    return [mine[b * batch_size:(b + 1) * batch_size].tolist() for b in range(nb)]


def collate(samples: list[dict], state_dim: int | None = None, resolution: int | None = None,
            psi_dim: int | None = None) -> dict:
    """Stack decoded samples: image (B,H,W,3) f32, jacobian (B,K,H,W,3) f32 or None, state (B,S) f64.  With
    ``resolution`` / ``psi_dim`` (the manifest's) every sample is checked against them, so that the message names
    the sample that is off (not its neighbour in the batch) and a manifest that misstates them is caught."""
    first = samples[0]
    for s in samples:
        where = f"sample {s['key']} in {s.get('url', '?')}"
        if state_dim is not None and s["state"].shape != (state_dim,):
            raise RispError(f"{where}: state has shape {tuple(s['state'].shape)}, expected ({state_dim},)")
        if resolution is not None and s["image"].shape != (resolution, resolution, 3):
            raise RispError(f"{where}: image has shape {tuple(s['image'].shape)}, but the manifest says "
                            f"{resolution}×{resolution} pixels")
        if psi_dim is not None and s["psi"] is not None and tuple(s["psi"].shape) != (psi_dim,):
            raise RispError(f"{where}: psi has shape {tuple(s['psi'].shape)}, but the manifest names {psi_dim} "
                            "rendering parameters")
        if (psi_dim is not None and resolution is not None and s["jacobian"] is not None
                and tuple(s["jacobian"].shape) != (psi_dim, resolution, resolution, 3)):
            raise RispError(f"{where}: jacobian has shape {tuple(s['jacobian'].shape)}, expected "
                            f"({psi_dim}, {resolution}, {resolution}, 3) from the manifest")
        if s["image"].shape != first["image"].shape:
            raise RispError(f"sample {s['key']} in {s.get('url', '?')}: image shape {s['image'].shape} differs "
                            f"from {first['image'].shape}")
        for field in ("image", "state", "jacobian", "psi"):  # ψ: recorded with the batch (its look), never NaN
            if s[field] is not None and not np.isfinite(s[field]).all():
                raise RispError(f"sample {s['key']} in {s.get('url', '?')}: {field} contains NaN or inf")
    out = {
        "key": [s["key"] for s in samples],
        "image": torch.from_numpy(np.stack([s["image"] for s in samples]).astype(np.float32)),
        "state": torch.from_numpy(np.stack([s["state"] for s in samples]).astype(np.float64)),
        "psi": torch.from_numpy(np.stack([s["psi"] for s in samples]).astype(np.float64)),
        "jacobian": None,
    }
    if first["jacobian"] is not None:
        out["jacobian"] = torch.from_numpy(np.stack([s["jacobian"] for s in samples]).astype(np.float32))
    return out


class _Collate:
    """Picklable collate function bound to the expected state dimension and the manifest's resolution and ψ count."""

    def __init__(self, state_dim: int | None, resolution: int | None = None, psi_dim: int | None = None):
        self.state_dim, self.resolution, self.psi_dim = state_dim, resolution, psi_dim

    def __call__(self, samples: list[dict]) -> dict:
        return collate(samples, self.state_dim, self.resolution, self.psi_dim)


class _WorkerInit:
    """A DataLoader's worker_init_fn: one torch thread (workers decode EXRs; the cores are the training process's),
    and the worker ends with the process that made the DataLoader (risp_data.processes.exit_with: a worker that
    starts while its parent is killed would otherwise wait on its queue forever)."""

    def __init__(self) -> None:
        from risp_data.processes import start_time

        self.parent, self.started = os.getpid(), start_time(os.getpid())

    def __call__(self, _: int) -> None:
        from risp_data.processes import exit_with

        torch.set_num_threads(1)
        exit_with(self.parent, self.started)


def loader_generator() -> torch.Generator:
    """A DataLoader's own generator: without one, every pass over a DataLoader draws its workers' base seed from
    torch's global generator, moving the caller's RNG.  Nothing here depends on that seed (the sample order is
    seeded explicitly, the workers draw nothing), so a fixed one keeps fit() off the caller's RNG."""
    return torch.Generator().manual_seed(0)


def make_loader(shards: ShardSet, *, seed: int, epoch: int, batch_size: int, workers: int, need_jacobian: bool,
                rank: int = 0, world_size: int = 1, shuffle_buffer: int = 256,
                state_dim: int | None = None) -> torch.utils.data.DataLoader:
    """A training DataLoader over this rank's share of ``epoch``: full batches only (module docstring)."""
    if need_jacobian and not shards.has_jacobian:
        raise RispError(f"shard folder {shards.folder} was rendered without Jacobians (--no-jacobian); "
                        "the regularizers need them: use --reg none or render with Jacobians")
    fn = _Collate(state_dim, shards.resolution, len(shards.psi_names))
    if shards.format == "wds":
        nw = effective_workers(len(shards.urls), world_size, workers)
        ds = WdsStream(shards.urls, seed, epoch, shuffle_buffer, need_jacobian, rank, resolution=shards.resolution,
                       world_size=world_size)
        return torch.utils.data.DataLoader(ds, batch_size=batch_size, num_workers=nw, collate_fn=fn,
                                           drop_last=True, persistent_workers=False, worker_init_fn=_WorkerInit(),
                                           generator=loader_generator())
    batches = zarr_batches(shards.num_samples, seed, epoch, batch_size, rank, world_size)
    ds = ZarrSamples(shards.folder, need_jacobian)
    return torch.utils.data.DataLoader(ds, batch_sampler=batches, num_workers=max(0, workers), collate_fn=fn,
                                       worker_init_fn=_WorkerInit(), generator=loader_generator())


def iter_samples(shards: ShardSet, need_jacobian: bool = False) -> Iterator[dict]:
    """All complete samples in shard order, one at a time (for statistics and evaluation)."""
    if shards.format == "zarr":
        ds = ZarrSamples(shards.folder, need_jacobian)
        for i in range(len(ds)):
            yield ds[i]
        return
    yield from WdsStream(shards.urls, 0, 0, 0, need_jacobian, rank=0, shuffle=False, split=False,
                         resolution=shards.resolution)


def iter_batches(shards: ShardSet, batch_size: int, need_jacobian: bool = False, state_dim: int | None = None,
                 limit: int | None = None) -> Iterator[dict]:
    """Sequential batches of all samples (the last one may be short), at most ``limit`` samples."""
    buf: list[dict] = []
    seen = 0
    for s in iter_samples(shards, need_jacobian):
        if limit is not None and seen >= limit:
            break
        buf.append(s)
        seen += 1
        if len(buf) == batch_size:
            yield collate(buf, state_dim, shards.resolution, len(shards.psi_names))
            buf = []
    if buf:
        yield collate(buf, state_dim, shards.resolution, len(shards.psi_names))
