"""zarr v3 store ``data.zarr`` (docs/formats.md, "zarr").

Arrays (float32 images and Jacobians, float64 states and ψ), each sharded along the sample axis with
one zarr shard = one shard task = ``shard_size`` samples, and one inner chunk per sample:

    images     (N, H, W, 3)      dimension_names (sample, y, x, channel)
    jacobians  (N, K, H, W, 3)   dimension_names (sample, psi, y, x, channel)   [full layout]
    jacobian_planes (N, P, H, W) dimension_names (sample, plane, y, x)          [own-channel layout: the
    jacobian_rest   (N, R, H, W) dimension_names (sample, plane, y, x)           stored / other planes,
                                 attribute ``planes`` = [[ψ name, channel], …] per plane]
    (no Jacobian array with --no-jacobian)
    states     (N, S)            dimension_names (sample, state)
    psi        (N, K)            dimension_names (sample, psi)

Unwritten samples read as NaN (the fill value).  Each writer writes whole shards at once: writing one
sample at a time rewrites the whole shard (5–26 ms/sample, ../shared/NOTES.md).  Inner chunks are
zstd-compressed with the zstd frame checksum on, and the shard index carries a crc32c, so corrupt bytes
fail loudly instead of decoding to wrong numbers.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from ..errors import RispError, message_line
from .layout import channel_map, from_planes, is_compact, plane_lists, to_planes
from .manifest import load_manifest, repair_hint

ZARR_DIR = "data.zarr"
_DIMS = {
    "images": ("sample", "y", "x", "channel"),
    "jacobians": ("sample", "psi", "y", "x", "channel"),
    "jacobian_planes": ("sample", "plane", "y", "x"),
    "jacobian_rest": ("sample", "plane", "y", "x"),
    "states": ("sample", "state"),
    "psi": ("sample", "psi"),
}
_RUNTIME = {"write_empty_chunks": True}  # a shard file always exists once written, even if all zeros
# Integrity (docs/formats.md, "Integrity guarantees"): each shard file is written atomically by zarr (temp
# ``*.partial`` + rename), and a shard's ``states`` file is removed first and written last, so a plain zarr
# reader never sees a sample whose state row is finite while another of its arrays is unwritten or stale.
WRITE_ORDER = ("jacobians", "jacobian_planes", "jacobian_rest", "images", "psi", "states")
PLANE_ARRAYS = ("jacobian_planes", "jacobian_rest")
COMPLETE_ATTR = "complete_shards"  # root attribute: indices of the shards listed in the manifest


def array_shapes(n: int, resolution: int, psi_names: list[str], s: int, jacobian: bool,
                 channels: dict[str, str] | None = None) -> dict[str, tuple[int, ...]]:
    """Shapes of the store's arrays; ``channels`` (risp_data.shards.layout) picks the Jacobian layout."""
    shapes = {"images": (n, resolution, resolution, 3)}
    if jacobian and channels and is_compact(channels):
        for name, planes in zip(PLANE_ARRAYS, plane_lists(psi_names, channels)):
            shapes[name] = (n, len(planes), resolution, resolution)
    elif jacobian:
        shapes["jacobians"] = (n, len(psi_names), resolution, resolution, 3)
    shapes.update(states=(n, s), psi=(n, len(psi_names)))
    return shapes


def manifest_shapes(manifest: dict[str, Any], n: int | None = None, resolution: int | None = None):
    """:func:`array_shapes` of a folder's manifest (``n``/``resolution`` overridable: only names and ranks
    matter to some callers)."""
    return array_shapes(manifest["n"] if n is None else n, manifest["resolution"] if resolution is None else resolution,
                        list(manifest["psi"]["names"]), len(manifest["state_names"]), manifest["jacobian"],
                        channel_map(manifest))


def create_store(folder: str, manifest: dict[str, Any]) -> None:
    """Create ``data.zarr`` with empty arrays for the manifest's job (metadata only, no chunk data)."""
    import zarr
    from zarr.codecs import ZstdCodec

    psi_names = list(manifest["psi"]["names"])
    state_names = list(manifest["state_names"])
    channels = channel_map(manifest)
    root_attrs = {
        k: manifest[k] for k in ("env", "domain", "resolution", "spp", "variant", "seed", "n", "shard_size")
    }
    root_attrs.update(psi_names=psi_names, state_names=state_names, risp_format=manifest["format"],
                      jacobian_channels=channels)
    root_attrs[COMPLETE_ATTR] = []
    root = zarr.open_group(os.path.join(folder, ZARR_DIR), mode="w", attributes=root_attrs)
    planes = dict(zip(PLANE_ARRAYS, plane_lists(psi_names, channels)))
    for name, shape in manifest_shapes(manifest).items():
        dtype = "float32" if name in ("images", "jacobians", *PLANE_ARRAYS) else "float64"
        attrs = {"psi_names": psi_names, "state_names": state_names}
        if name in planes:
            attrs["planes"] = planes[name]
        root.create_array(
            name,
            shape=shape,
            dtype=dtype,
            chunks=(1, *shape[1:]),
            shards=(manifest["shard_size"], *shape[1:]),
            compressors=ZstdCodec(level=3, checksum=True),
            fill_value=float("nan"),
            dimension_names=_DIMS[name],
            attributes=attrs,
        )


def shard_file(folder: str, name: str, shard_index: int, ndim: int) -> str:
    """Relative path of array ``name``'s zarr shard file for shard task ``shard_index``."""
    return f"{ZARR_DIR}/{name}/c/" + "/".join([str(shard_index)] + ["0"] * (ndim - 1))


def write_zarr_shard(folder: str, shard_index: int, start: int, arrays: dict[str, np.ndarray | None],
                     psi_names: list[str], channels: dict[str, str] | None = None) -> list[str]:
    """Write one whole shard of every array (``arrays`` from :func:`stack_samples`); with an own-channel
    ``channels`` map (the manifest's, the store's layout) the (n, K, H, W, 3) ``jacobians`` are written as
    the planes of ``jacobian_planes`` and ``jacobian_rest``; returns relative paths."""
    import zarr

    arrays = dict(arrays)
    if channels and is_compact(channels) and arrays.get("jacobians") is not None:
        jac = arrays.pop("jacobians")
        for name, planes in zip(PLANE_ARRAYS, plane_lists(psi_names, channels)):
            arrays[name] = to_planes(jac, psi_names, planes)
    opened = {name: zarr.open_array(os.path.join(folder, ZARR_DIR, name), mode="r+", config=_RUNTIME)
              for name in WRITE_ORDER if arrays.get(name) is not None}
    rels = {name: shard_file(folder, name, shard_index, arr.ndim) for name, arr in opened.items()}
    for name in reversed(WRITE_ORDER):  # states first: a killed run's shard never merges into new data
        stale = os.path.join(folder, rels[name]) if name in rels else None
        if stale and os.path.exists(stale):
            os.unlink(stale)
    for name, arr in opened.items():
        data = arrays[name]
        size = arr.shards[0]
        if start != shard_index * size or data.shape[0] != min(size, arr.shape[0] - start):
            raise ValueError(f"samples [{start}, {start + data.shape[0]}) are not zarr shard {shard_index} of {name}")
        try:
            arr[start : start + data.shape[0]] = data
        except OSError as e:  # disk full and the like: name the shard file (zarr's error names none)
            raise OSError(e.errno, e.strerror or str(e), e.filename or os.path.join(folder, rels[name])) from e
    return [rels[name] for name in _DIMS if name in rels]


def mark_complete_shards(folder: str, manifest: dict[str, Any]) -> None:
    """Record the manifest's complete shards in the store's root attribute ``complete_shards`` (written by
    the parent process only, atomically by zarr), where plain zarr readers can see which samples to trust."""
    import zarr

    try:
        group = zarr.open_group(os.path.join(folder, ZARR_DIR), mode="r+")
    except Exception as e:  # noqa: BLE001 - damaged root metadata (rendering checks the store before: a race)
        raise RispError(f"corrupt zarr store {os.path.join(folder, ZARR_DIR)}: {type(e).__name__}"
                        f"{repair_hint(folder)}") from None
    done = sorted(int(r["index"]) for r in manifest["shards"])
    if list(group.attrs.get(COMPLETE_ATTR, [])) != done:
        group.attrs[COMPLETE_ATTR] = done


class ZarrDataset:
    """Map-style, torch-free reader over the complete shards of ``folder/data.zarr``.

    ``ds[i]`` returns the same dict as :func:`risp_data.shards.decode_wds_sample` (``meta`` carries the
    manifest-level fields and the sample's global index).  Only shards listed in the manifest are visible.
    """

    def __init__(self, folder: str):
        self.folder = folder
        self.manifest = load_manifest(folder)
        m = self.manifest
        if "zarr" not in m["formats"]:
            raise RispError(f"shard folder {folder} holds no zarr store (formats: {', '.join(m['formats'])})")
        self._arrays = self._open()
        self._ranges = []  # (start, stop) of complete shards, ascending
        for rec in m["shards"]:
            for rel, info in rec["files"].items():
                if rel.startswith(ZARR_DIR + "/"):
                    p = os.path.join(folder, rel)
                    if not os.path.exists(p):
                        raise RispError(f"zarr shard file missing: {p}{repair_hint(folder)}")
                    if os.path.getsize(p) != info["bytes"]:
                        raise RispError(f"truncated or corrupt zarr shard file {p}: size differs from the manifest"
                                        f"{repair_hint(folder)}")
            self._ranges.append((rec["start"], rec["stop"], rec["index"]))
        self._ranges.sort()
        self._offsets = np.cumsum([0] + [b - a for a, b, _ in self._ranges])
        self.psi_names = list(m["psi"]["names"])
        self.state_names = list(m["state_names"])
        # samples whose off-channel planes are not all +0.0 (risp_data.shards.writer): only they read jacobian_rest
        self._fallback = {int(i) for rec in m["shards"] for i in rec.get("jacobian_fallback", {})}

    def _open(self) -> dict:
        import zarr

        path = os.path.join(self.folder, ZARR_DIR)
        try:
            group = zarr.open_group(path, mode="r")
            arrays = {name: group[name] for name in _DIMS if name in group}
        except (MemoryError, PermissionError):  # the machine's, not the store's: said as such (cli_util), no repair
            raise
        except Exception as e:
            raise RispError(f"corrupt zarr store {path}: {type(e).__name__}: {message_line(e)}"
                            f"{repair_hint(self.folder)}") from None
        shapes = manifest_shapes(self.manifest)
        missing = [name for name in shapes if name not in arrays]
        if missing:  # an array's zarr.json deleted: the array is not there for zarr (it was a KeyError)
            raise RispError(f"corrupt zarr store {path}: the array {missing[0]} is missing{repair_hint(self.folder)}")
        for name, shape in shapes.items():  # as the writer's check (generate._zarr_store_ok): a hand-edited
            # zarr.json of another shape would otherwise make a read allocate that shape's fill value
            if tuple(arrays[name].shape) != tuple(shape):
                raise RispError(f"corrupt zarr store {path}: the array {name} has shape {tuple(arrays[name].shape)}, "
                                f"the manifest's {tuple(shape)}{repair_hint(self.folder)}")
        return arrays

    def __getstate__(self) -> dict:
        # DataLoader workers get a copy without open zarr handles and reopen the store themselves
        state = dict(self.__dict__)
        state["_arrays"] = None
        return state

    def __len__(self) -> int:
        return int(self._offsets[-1])

    def global_index(self, i: int) -> tuple[int, int]:
        """(global sample index, shard index) of dataset position ``i``."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} complete samples")
        i %= len(self)
        r = int(np.searchsorted(self._offsets, i, side="right")) - 1
        start, _, shard = self._ranges[r]
        return start + i - int(self._offsets[r]), shard

    def __getitem__(self, i: int) -> dict[str, Any]:
        from .sample import sample_key

        g, shard = self.global_index(i)
        if self._arrays is None:
            self._arrays = self._open()
        out = {}
        for name, arr in self._arrays.items():
            if name == "jacobian_rest" and g not in self._fallback:  # exact sample: its rest is all +0.0
                continue
            try:
                out[name] = np.asarray(arr[g])
            except (MemoryError, PermissionError):  # the machine's, not the file's (cli_util says them)
                raise
            except Exception as e:
                rel = shard_file(self.folder, name, shard, arr.ndim)
                raise RispError(
                    f"corrupt zarr shard file {os.path.join(self.folder, rel)}: {type(e).__name__}: "
                    f"{message_line(e)}{repair_hint(self.folder)}"
                ) from None
        if not np.isfinite(out["states"]).all():  # listed but unwritten (NaN fill): never hand it out as data
            rel = shard_file(self.folder, "states", shard, 2)
            raise RispError(f"zarr shard file {os.path.join(self.folder, rel)}: sample {g} is unwritten (NaN) "
                            f"although the manifest lists its shard{repair_hint(self.folder)}")
        if "jacobian_planes" in out:  # own-channel layout: the stored planes (+ the rest where not exact)
            planes = [(out.pop(n), list(self._arrays[n].attrs["planes"])) for n in PLANE_ARRAYS if n in out]
            out["jacobians"] = from_planes(planes, self.psi_names)
        m = self.manifest
        meta = {k: m[k] for k in ("env", "domain", "resolution", "spp", "seed", "variant")}
        meta.update(index=g, state_names=self.state_names, psi_names=self.psi_names)
        return {
            "key": sample_key(g),
            "image": out["images"],
            "jacobian": out.get("jacobians"),
            "state": out["states"],
            "psi": out["psi"],
            "meta": meta,
        }
