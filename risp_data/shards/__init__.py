"""Shard formats written by ``risp-data render``: webdataset tars, a zarr v3 store and a manifest.

    from risp_data.shards import load_manifest, wds_urls, decode_wds_sample, iter_wds, ZarrDataset, verify_checksums

Field-by-field description: docs/formats.md.  Nothing is imported from mitsuba here.
"""

from .manifest import load_manifest, verify_checksums
from .sample import Sample, sample_key
from .wds import decode_wds_sample, iter_wds, wds_urls
from .zarr_store import ZarrDataset

__all__ = [
    "Sample",
    "ZarrDataset",
    "decode_wds_sample",
    "iter_wds",
    "load_manifest",
    "sample_key",
    "verify_checksums",
    "wds_urls",
]
