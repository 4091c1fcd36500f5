"""Test helpers for shard folders of either Jacobian layout (docs/formats.md)."""

from __future__ import annotations

import os

import numpy as np


def scale_stored_jacobian(folder: str, rows: list[int], psi: str, factor: float) -> str:
    """Multiply ψ's stored ∂I/∂ψ of samples ``rows`` (of zarr shard 0, which holds samples 0 … shard_size−1)
    by ``factor`` in the zarr store — in the ``jacobians`` array (full layout) or in the ``jacobian_planes``
    that hold ψ (own-channel layout) — as a writer with a wrong J would have; returns the relative path of the
    shard file changed."""
    import zarr

    from risp_data.shards.zarr_store import shard_file

    g = zarr.open_group(os.path.join(folder, "data.zarr"), mode="r+")
    names = list(g.attrs["psi_names"])
    name = "jacobians" if "jacobians" in g else "jacobian_planes"
    arr = g[name]
    planes = ([names.index(psi)] if name == "jacobians" else
              [p for p, (n, _) in enumerate(arr.attrs["planes"]) if n == psi])
    n = arr.shards[0]
    block = np.asarray(arr[0:n])
    for r in rows:
        for p in planes:
            block[r, p] *= factor
    arr[0:n] = block
    return shard_file("", name, 0, arr.ndim)
