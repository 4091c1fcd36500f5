"""Write one shard task's samples in every requested format, hash the files, mark the shard complete."""

from __future__ import annotations

from typing import Any

from .manifest import file_record, write_marker
from .sample import Sample, stack_samples
from .wds import write_wds_shard
from .zarr_store import write_zarr_shard

FORMATS = ("wds", "zarr")


def write_shard(folder: str, formats: tuple[str, ...], shard_index: int, samples: list[Sample]) -> dict[str, Any]:
    """Write ``samples`` (one contiguous index range) as shard ``shard_index``; returns its manifest record.

    The completion marker is written last (temp name + rename), after every file is in place and hashed,
    so a killed writer leaves a shard that readers and resume treat as missing.
    """
    samples = sorted(samples, key=lambda s: s.index)
    start, stop = samples[0].index, samples[-1].index + 1
    if stop - start != len(samples):
        raise ValueError(f"shard {shard_index}: sample indices are not contiguous")
    rels: list[str] = []
    if "wds" in formats:
        rels.append(write_wds_shard(folder, shard_index, samples))
    if "zarr" in formats:
        rels.extend(write_zarr_shard(folder, shard_index, start, stack_samples(samples)))
    record = {
        "index": shard_index,
        "start": start,
        "stop": stop,
        "files": {rel: file_record(folder, rel) for rel in rels},
    }
    write_marker(folder, record)
    return record
