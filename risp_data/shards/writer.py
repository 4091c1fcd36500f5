"""Write one shard task's samples in every requested format, hash the files, mark the shard complete."""

from __future__ import annotations

from typing import Any

from .layout import channel_map, is_compact, sample_channels
from .manifest import file_record, load_manifest, write_marker
from .sample import Sample, stack_samples
from .wds import write_wds_shard
from .zarr_store import write_zarr_shard

FORMATS = ("wds", "zarr")


def write_shard(folder: str, formats: tuple[str, ...], shard_index: int, samples: list[Sample]) -> dict[str, Any]:
    """Write ``samples`` (one contiguous index range) as shard ``shard_index``; returns its manifest record.

    The completion marker is written last (temp name + rename), after every file is in place and hashed,
    so a killed writer leaves a shard that readers and resume treat as missing.  The Jacobian layout is the
    one the folder's manifest records (``jacobian_storage``; risp_data.shards.layout), also on resume.
    """
    manifest = load_manifest(folder)
    channels = channel_map(manifest)
    samples = sorted(samples, key=lambda s: s.index)
    start, stop = samples[0].index, samples[-1].index + 1
    if stop - start != len(samples):
        raise ValueError(f"shard {shard_index}: sample indices are not contiguous")
    names = list(manifest["psi"]["names"])
    stored = [sample_channels(s.jacobian, names, channels) if s.jacobian is not None and is_compact(channels)
              else None for s in samples]
    # samples that keep all three channels of a ψ the map compacts (another channel not exactly +0.0)
    fallback = {str(s.index): sorted(n for n in names if kept[n] != channels[n])
                for s, kept in zip(samples, stored) if kept is not None and kept != channels}
    rels: list[str] = []
    if "wds" in formats:
        rels.append(write_wds_shard(folder, shard_index, samples, stored))
    if "zarr" in formats:
        rels.extend(write_zarr_shard(folder, shard_index, start, stack_samples(samples), names, channels))
    record = {
        "index": shard_index,
        "start": start,
        "stop": stop,
        "files": {rel: file_record(folder, rel) for rel in rels},
    }
    if fallback:  # the zarr reader adds the jacobian_rest planes of these samples only
        record["jacobian_fallback"] = fallback
    write_marker(folder, record)
    return record
