"""Training data held in memory: every sample of a shard folder decoded once, then batched by index.

Why: a webdataset sample is decoded anew in every epoch (sha256 of each member, the image EXR and, for
the regularizers, the Jacobian EXR): 2–3 ms per sample on this machine, i.e. 30–50 ms per batch of 16,
more than the `cpu` preset's network step itself (docs/PERFORMANCE.md §Training data in memory).  A
10 000-sample set with K = 8 Jacobians at 64×64 decodes to ≈ 4 GB of float32, which a training machine
holds, so ``risp-train fit --cache auto`` (the default) decodes the folder once — checksums and all the
checks of the streamed path — into four tensors and afterwards only indexes them:

    image (N, H, W, 3) float32 · jacobian (N, K, H, W, 3) float32 or None · state (N, S) float64 · psi (N, K) float64

Position p of these tensors is the p-th complete sample in shard order (the zarr store's map-style order),
and an epoch's batches are the zarr reader's: the permutation of positions seeded by (seed, epoch), split
over ranks (``data.zarr_batches``).  A run with ``--cache memory`` is therefore bitwise the run that streams
the zarr store, and its data position (epoch, batch) resumes the same way; it differs from a *streamed
webdataset* run only in the order of the samples (that path shuffles shards and a bounded buffer).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Iterator

import torch

from risp_data.errors import RispError
from risp_data.generate import available_memory  # one rule: MemAvailable, the cgroup limit, RLIMIT_AS

from .data import ShardSet, WdsStream, ZarrSamples, _Collate, _WorkerInit, loader_generator, zarr_batches

CACHE_MODES = ("auto", "memory", "stream")
# --cache auto keeps the data in memory when it needs at most this share of the memory available at the start
AUTO_MEMORY_SHARE = 0.5
_F32, _F64 = 4, 8


@dataclass(frozen=True)
class MemorySet:
    """The decoded samples of one shard folder (module docstring); ``keys[p]`` names position p."""

    folder: str
    keys: tuple[str, ...]
    image: torch.Tensor
    state: torch.Tensor
    psi: torch.Tensor
    jacobian: torch.Tensor | None

    def __len__(self) -> int:
        return len(self.keys)

    @property
    def nbytes(self) -> int:
        tensors = (self.image, self.state, self.psi) + ((self.jacobian,) if self.jacobian is not None else ())
        return sum(t.numel() * t.element_size() for t in tensors)

    def batch(self, positions: list[int]) -> dict:
        """The batch of ``positions``, as ``data.collate`` returns it for the same samples."""
        idx = torch.as_tensor(positions, dtype=torch.long)
        return {"key": [self.keys[p] for p in positions], "image": self.image[idx], "state": self.state[idx],
                "psi": self.psi[idx], "jacobian": None if self.jacobian is None else self.jacobian[idx]}


def estimate_bytes(shards: ShardSet, need_jacobian: bool) -> int:
    """Bytes of the tensors :func:`load_memory_set` allocates for ``shards`` (from the manifest alone)."""
    n, res = shards.num_samples, shards.resolution
    k, s = len(shards.psi_names), len(shards.state_names)
    per = res * res * 3 * _F32 + (s + k) * _F64 + (k * res * res * 3 * _F32 if need_jacobian else 0)
    return n * per


def resolve_cache(mode: str, shards: ShardSet, need_jacobian: bool, available: int | None = None,
                  processes: int = 1) -> str:
    """``memory`` or ``stream`` for ``--cache mode``: ``auto`` keeps the data in memory when it needs at most
    AUTO_MEMORY_SHARE of the available memory; ``memory`` insists (one clear error when it cannot fit).
    ``processes``: the training processes on this machine (torchrun's LOCAL_WORLD_SIZE), each of which holds the
    whole set: each may count on its share of the memory only."""
    if mode not in CACHE_MODES:
        raise RispError(f"unknown --cache {mode!r}; choose one of: {', '.join(CACHE_MODES)}")
    if mode == "stream":
        return "stream"
    need = estimate_bytes(shards, need_jacobian)
    avail = available_memory() if available is None else available
    if avail is not None:
        avail //= max(1, processes)
    if mode == "memory":
        if avail is not None and need > avail:
            each = f" for each of {processes} processes" if processes > 1 else ""
            raise RispError(f"--cache memory: {shards.folder} decodes to {need / 2**30:.1f} GiB but only "
                            f"{avail / 2**30:.1f} GiB of memory is available{each}; use --cache stream")
        return "memory"
    return "memory" if avail is not None and need <= AUTO_MEMORY_SHARE * avail else "stream"


def _positions(shards: ShardSet) -> dict[int, int]:
    """Global sample index → position (complete shards in index order, as the zarr store counts them)."""
    out, p = {}, 0
    for start, count in zip(shards.starts, shards.counts):
        for g in range(start, start + count):
            out[g] = p
            p += 1
    return out


def load_memory_set(shards: ShardSet, *, need_jacobian: bool, workers: int = 0, state_dim: int | None = None,
                    progress: bool = False) -> MemorySet:
    """Decode every complete sample of ``shards`` once, with the streamed path's checks (member sha256, the
    manifest's ranges and counts, shapes, NaN/inf), ``workers`` processes decoding whole shards in parallel."""
    if need_jacobian and not shards.has_jacobian:
        raise RispError(f"shard folder {shards.folder} was rendered without Jacobians (--no-jacobian); "
                        "the regularizers need them: use --reg none or render with Jacobians")
    n, res = shards.num_samples, shards.resolution
    k, s = len(shards.psi_names), len(shards.state_names)
    pos = _positions(shards)
    image = torch.empty((n, res, res, 3), dtype=torch.float32)
    state = torch.empty((n, s), dtype=torch.float64)
    psi = torch.empty((n, k), dtype=torch.float64)
    jac = torch.empty((n, k, res, res, 3), dtype=torch.float32) if need_jacobian else None
    keys: list[str | None] = [None] * n
    fn = _Collate(state_dim, res, k)
    if shards.format == "wds":  # each worker decodes whole shards; every rank holds every sample
        ds = WdsStream(shards.urls, 0, 0, 0, need_jacobian, rank=0, shuffle=False, split=True, split_nodes=False,
                       resolution=shards.resolution)
        nw = max(0, min(workers, len(shards.urls)))
    else:
        ds = ZarrSamples(shards.folder, need_jacobian)
        nw = max(0, workers)
    loader = torch.utils.data.DataLoader(ds, batch_size=64, num_workers=nw, collate_fn=fn,
                                         worker_init_fn=_WorkerInit() if nw else None, generator=loader_generator())
    from tqdm.auto import tqdm

    with tqdm(total=n, disable=not progress, unit="sample", desc=f"decode {os.path.basename(shards.folder)}") as bar:
        for b in loader:
            for i, key in enumerate(b["key"]):
                g = int(key[1:]) if key[:1] == "s" and key[1:].isdigit() else -1
                p = pos.get(g)
                if p is None or keys[p] is not None:
                    raise RispError(f"shard folder {shards.folder}: sample {key!r} is not a complete sample of the "
                                    "manifest, or appears twice")
                keys[p] = key
                image[p], state[p], psi[p] = b["image"][i], b["state"][i], b["psi"][i]
                if jac is not None:
                    jac[p] = b["jacobian"][i]
            bar.update(len(b["key"]))
    missing = [p for p, key in enumerate(keys) if key is None]
    if missing:
        raise RispError(f"shard folder {shards.folder}: {len(missing)} of {n} samples listed in the manifest were "
                        "not found in its shards")
    return MemorySet(shards.folder, tuple(keys), image, state, psi, jac)  # type: ignore[arg-type]


def memory_batches(mset: MemorySet, *, seed: int, epoch: int, batch_size: int, rank: int = 0,
                   world_size: int = 1) -> Iterator[dict]:
    """This rank's batches of ``epoch``: the zarr reader's plan (``data.zarr_batches``) over positions."""
    for positions in zarr_batches(len(mset), seed, epoch, batch_size, rank, world_size):
        yield mset.batch(positions)


__all__ = ["CACHE_MODES", "MemorySet", "available_memory", "estimate_bytes", "load_memory_set", "memory_batches", "resolve_cache"]
