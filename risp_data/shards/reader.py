"""Readers of a shard folder, re-exported from :mod:`risp_data.shards` (docs/formats.md, "Reading")."""

from __future__ import annotations

from .manifest import load_manifest, verify_checksums
from .wds import decode_wds_sample, iter_wds, wds_urls
from .zarr_store import ZarrDataset

__all__ = [
    "ZarrDataset",
    "complete_indices",
    "decode_wds_sample",
    "iter_wds",
    "load_manifest",
    "read_samples",
    "verify_checksums",
    "wds_urls",
]


def complete_indices(manifest: dict) -> list[int]:
    """Global indices of every sample in a complete shard, ascending."""
    out: list[int] = []
    for rec in sorted(manifest["shards"], key=lambda r: r["start"]):
        out.extend(range(rec["start"], rec["stop"]))
    return out


def read_samples(folder: str, indices: list[int]) -> dict[int, dict]:
    """Decoded samples with the given global indices (zarr when present: random access; else webdataset)."""
    m = load_manifest(folder)
    wanted = set(indices)
    if "zarr" in m["formats"]:
        ds = ZarrDataset(folder)
        pos = {g: p for p, g in enumerate(complete_indices(m))}
        missing = wanted - pos.keys()
        if missing:
            from ..errors import RispError

            raise RispError(f"samples {sorted(missing)[:5]} are not in a complete shard of {folder}")
        return {g: ds[pos[g]] for g in sorted(wanted)}
    out = {}
    for s in iter_wds(folder):
        if s["meta"]["index"] in wanted:
            out[s["meta"]["index"]] = s
            if len(out) == len(wanted):
                break
    return out
