"""How a folder stores its Jacobian stacks: in full, or own-channel planes where that is exact (issue 9).

J = [∂I/∂ψ_1 … ∂I/∂ψ_K] has shape (K, H, W, 3).  For a material colour ψ_j (``object_r``, ``floor_g`` …) the
``rgb`` variant never mixes channels, so ∂I/∂ψ_j is non-zero only in ψ_j's own channel (docs/rendering.md,
"The fast Jacobian path").  The manifest's ``jacobian_storage.channels`` maps every ψ name to the channels
stored for it: ``"RGB"`` (all three) or one of ``"R"``, ``"G"``, ``"B"`` (its own channel only; the others are
stored nowhere and read back as +0.0).  Folders written before format_version 2 have no such field: all
``"RGB"``.

Exactness is checked per sample and per ψ (:func:`sample_channels`): a ψ is stored as one channel only when
its other two channels are bitwise +0.0 in that sample, so expanding gives back the very same bits;
otherwise that sample keeps all three channels of that ψ (webdataset: a full ``<name>.RGB`` group and its json's
``jacobian_channels`` says ``"RGB"``; zarr, whose arrays have one shape for all samples: the other channels
are the ``jacobian_rest`` planes — +0.0 in exact samples, ≈ 30 bytes of zstd each — and the shard's manifest
record lists the samples that fell back, the only ones whose ``jacobian_rest`` the project's reader reads).

Nothing here imports mitsuba or torch.
"""

from __future__ import annotations

from typing import Any

import numpy as np

RGB = "RGB"
LAYOUTS = ("own-channel", "full")
STORAGE_MEANING = (
    "channels[psi] = the colour channels of dI/dpsi stored per sample: 'RGB' all three; 'R', 'G' or 'B' only "
    "that channel, where the other two are exactly +0.0 (a material colour's derivative lives in its own "
    "channel); a sample whose other channels are not exactly zero keeps all three (docs/formats.md)")


def storage_block(psi_names: list[str], own: dict[str, str], compact: bool) -> dict[str, Any]:
    """The manifest's ``jacobian_storage``: layout name, per-ψ stored channels, what they mean."""
    channels = {n: (own.get(n, RGB) if compact else RGB) for n in psi_names}
    return {"layout": "own-channel" if is_compact(channels) else "full", "channels": channels,
            "meaning": STORAGE_MEANING}


def channel_map(manifest: dict[str, Any]) -> dict[str, str]:
    """Stored channels per ψ name of a folder (all ``"RGB"`` in folders older than format_version 2)."""
    names = list(manifest["psi"]["names"])
    block = manifest.get("jacobian_storage") or {}
    channels = dict(block.get("channels") or {})
    out = {n: channels.get(n, RGB) for n in names}
    bad = {n: c for n, c in out.items() if c not in (RGB, "R", "G", "B")}
    if bad:
        raise ValueError(f"jacobian_storage.channels holds unknown channels {bad}")
    return out


def is_compact(channels: dict[str, str]) -> bool:
    return any(c != RGB for c in channels.values())


def _is_plus_zero(a: np.ndarray) -> bool:
    """All elements bitwise +0.0 (so that a zero-filled expansion restores the same bits; -0.0 does not)."""
    return not np.ascontiguousarray(a, dtype=np.float32).view(np.uint32).any()


def sample_channels(jacobian: np.ndarray, psi_names: list[str], channels: dict[str, str]) -> dict[str, str]:
    """The channels one sample actually stores: ``channels[name]`` where the other two channels of J_j are
    bitwise +0.0 in this sample, ``"RGB"`` where they are not (the fall-back keeps J exact)."""
    out = {}
    for j, name in enumerate(psi_names):
        c = channels.get(name, RGB)
        if c != RGB:
            others = [i for i in range(3) if i != RGB.index(c)]
            if not _is_plus_zero(jacobian[j][..., others]):
                c = RGB
        out[name] = c
    return out


# ------------------------------------------------------------------------------- zarr: plane arrays


def plane_lists(psi_names: list[str], channels: dict[str, str]) -> tuple[list[list[str]], list[list[str]]]:
    """(stored, rest): the [ψ name, channel] of every plane of the zarr arrays ``jacobian_planes`` (the
    channels the map keeps) and ``jacobian_rest`` (the others: zero in every exact sample), in ψ order."""
    stored, rest = [], []
    for name in psi_names:
        keep = channels.get(name, RGB)
        for c in RGB:
            (stored if c in keep else rest).append([name, c])
    return stored, rest


def to_planes(jacobians: np.ndarray, psi_names: list[str], planes: list[list[str]]) -> np.ndarray:
    """(n, K, H, W, 3) stacks → (n, P, H, W) planes in the order of ``planes``."""
    index = {n: j for j, n in enumerate(psi_names)}
    out = np.empty((jacobians.shape[0], len(planes), *jacobians.shape[2:4]), np.float32)
    for p, (name, c) in enumerate(planes):
        out[:, p] = jacobians[:, index[name], :, :, RGB.index(c)]
    return out


def from_planes(arrays: list[tuple[np.ndarray, list[list[str]]]], psi_names: list[str]) -> np.ndarray:
    """The (K, H, W, 3) stack of one sample from its plane arrays ``[(planes (P, H, W), plane list), …]``."""
    index = {n: j for j, n in enumerate(psi_names)}
    h, w = arrays[0][0].shape[1:]
    jac = np.zeros((len(psi_names), h, w, 3), np.float32)
    for data, planes in arrays:
        for p, (name, c) in enumerate(planes):
            jac[index[name], :, :, RGB.index(c)] = data[p]
    return jac
