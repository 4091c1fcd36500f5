"""webdataset shards: ``wds/shard-NNNNNN.tar``, one tar per shard task (docs/formats.md, "webdataset").

Per sample ``sNNNNNNNN`` the tar holds, in this order (members sorted by key, then name):

    sNNNNNNNN.image.exr      float32 RGB EXR (ZIP compression), channels R, G, B
    sNNNNNNNN.jacobian.exr   one multi-channel float32 EXR; channel group ``<psi_name>`` = ∂I/∂ψ_j
                             (channels ``<psi_name>.R/G/B``, or only the own channel ``<psi_name>.<c>``
                             where the json's ``jacobian_channels`` says so); absent in --no-jacobian shards
    sNNNNNNNN.json           metadata (env, domain, index, seed, render_seed, names, aux, resolution,
                             spp, member_sha256: the sha256 of every other member of the sample)
    sNNNNNNNN.psi.npy        (K,) float64, np.save(allow_pickle=False)
    sNNNNNNNN.state.npy      (S,) float64

Tars are reproducible: sorted members, fixed mtime, uid/gid 0, no user names.  No pickle anywhere.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import tarfile
from typing import Any, Iterator

import numpy as np

from ..errors import RispError
from .manifest import load_manifest, repair_hint
from .layout import RGB, is_compact
from .sample import Sample
from ..atomic import atomic_write

WDS_DIR = "wds"
MTIME = 0  # fixed member mtime: byte-identical tars for identical samples
MEMBERS = ("image.exr", "jacobian.exr", "json", "psi.npy", "state.npy")


def shard_name(shard_index: int) -> str:
    return f"{WDS_DIR}/shard-{shard_index:06d}.tar"


# --------------------------------------------------------------------------------------------- EXR


def encode_exr(channels: dict[str, np.ndarray]) -> bytes:
    """Float32 EXR bytes; ``channels`` maps a group name (``"RGB"`` or ``"<name>.RGB"``) to (H, W, 3)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    pixels = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    buf = io.BytesIO()
    with OpenEXR.File(header, pixels) as f:
        f.write(buf)
    return buf.getvalue()


def decode_exr(data: bytes, resolution: int | None = None) -> dict[str, np.ndarray]:
    """Channel groups of an EXR (``"RGB"``, ``"<name>.RGB"``) as (H, W, 3) float32 arrays.  ``resolution``: the
    size the folder's manifest says, checked from the header before the pixels are decoded (a small ZIP-compressed
    file can expand to gigabytes: a damaged or hostile shard must not exhaust memory first)."""
    import OpenEXR

    if resolution is not None:
        with OpenEXR.File(io.BytesIO(data), header_only=True) as f:
            (x0, y0), (x1, y1) = f.header()["dataWindow"]
        size = (int(y1) - int(y0) + 1, int(x1) - int(x0) + 1)
        if size != (resolution, resolution):
            raise ValueError(f"the EXR is {size[0]}×{size[1]} pixels, the folder's images {resolution}×{resolution}")
    with OpenEXR.File(io.BytesIO(data)) as f:
        return {k: np.asarray(v.pixels, dtype=np.float32) for k, v in f.channels().items()}


def encode_jacobian(jacobian: np.ndarray, psi_names: list[str], channels: dict[str, str] | None = None) -> bytes:
    """The (K, H, W, 3) stack as one EXR: per ψ_j a channel group ``<psi_name>.RGB``, or the single channel
    ``<psi_name>.<c>`` where ``channels[psi_name] = c`` (own-channel storage; the caller checked that the
    other two channels are +0.0: risp_data.shards.layout.sample_channels)."""
    if jacobian.shape[0] != len(psi_names):
        raise ValueError(f"jacobian has {jacobian.shape[0]} slices for {len(psi_names)} psi names")
    channels = channels or {}
    out = {}
    for j, name in enumerate(psi_names):
        c = channels.get(name, RGB)
        out[f"{name}.{c}"] = jacobian[j] if c == RGB else jacobian[j][..., RGB.index(c)]
    return encode_exr(out)


def decode_jacobian(data: bytes, psi_names: list[str], channels: dict[str, str] | None = None,
                    resolution: int | None = None) -> np.ndarray:
    """The full (K, H, W, 3) stack of a Jacobian EXR; ``channels`` (the sample's json ``jacobian_channels``,
    absent in old samples: all ``"RGB"``) says which channels each ψ stored, the others are +0.0."""
    groups = decode_exr(data, resolution)
    channels = channels or {}
    keys = [f"{n}.{channels.get(n, RGB)}" for n in psi_names]
    missing = [k for k in keys if k not in groups]
    if missing:
        raise ValueError(f"jacobian EXR lacks channel group(s) {', '.join(missing)}")
    first = groups[keys[0]]
    jac = np.zeros((len(psi_names), *first.shape[:2], 3), np.float32)
    for j, (name, key) in enumerate(zip(psi_names, keys)):
        c = channels.get(name, RGB)
        if c == RGB:
            jac[j] = groups[key]
        else:
            jac[j, ..., RGB.index(c)] = groups[key]
    return jac


# ------------------------------------------------------------------------------------------ writing


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(a, dtype=np.float64), allow_pickle=False)
    return buf.getvalue()


def sample_members(sample: Sample, stored: dict[str, str] | None = None) -> dict[str, bytes]:
    """The tar members of one sample, keyed by extension (without the key); ``stored``: the channels this
    sample stores per ψ (risp_data.shards.layout.sample_channels; None: all three, no json field)."""
    meta = dict(sample.meta)
    members = {
        "image.exr": encode_exr({"RGB": sample.image}),
        "psi.npy": _npy_bytes(sample.psi),
        "state.npy": _npy_bytes(sample.state),
    }
    if sample.jacobian is not None:
        if stored and is_compact(stored):
            meta["jacobian_channels"] = dict(stored)
        members["jacobian.exr"] = encode_jacobian(sample.jacobian, list(meta["psi_names"]), stored)
    # EXR and .npy carry no checksum of their own: the json records one per member, so a flipped
    # byte fails on read instead of decoding to wrong pixels.
    meta = dict(meta, member_sha256={k: hashlib.sha256(v).hexdigest() for k, v in sorted(members.items())})
    members["json"] = json.dumps(meta, sort_keys=True, allow_nan=False).encode()
    return members


def write_wds_shard(folder: str, shard_index: int, samples: list[Sample],
                    stored: list[dict[str, str] | None] | None = None) -> str:
    """Write one tar shard under a temporary name and rename it into place; returns its relative path.
    ``stored[i]``: the channels sample i stores per ψ (None: all three)."""
    rel = shard_name(shard_index)
    path = os.path.join(folder, rel)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with atomic_write(path, "wb", suffix=".tar") as f:
        with tarfile.open(fileobj=f, mode="w", format=tarfile.USTAR_FORMAT) as tar:
            stored = stored or [None] * len(samples)
            for sample, kept in sorted(zip(samples, stored), key=lambda p: p[0].index):
                for ext, data in sorted(sample_members(sample, kept).items()):
                    info = tarfile.TarInfo(f"{sample.key}.{ext}")
                    info.size = len(data)
                    info.mtime = MTIME
                    info.mode = 0o644
                    info.uid = info.gid = 0
                    info.uname = info.gname = ""
                    tar.addfile(info, io.BytesIO(data))
    return rel


# ------------------------------------------------------------------------------------------ reading


def _where(sample: dict[str, Any]) -> str:
    return f"shard {sample.get('__url__', '<unknown shard>')} key {sample.get('__key__', '<unknown key>')}"


def _repair(sample: dict[str, Any]) -> str:
    """The repair hint for a bad sample of ``FOLDER/wds/shard-*.tar`` (its ``__url__``), as the other readers give
    it; "" when the sample does not say where it came from."""
    url = sample.get("__url__")
    if not isinstance(url, str) or os.path.basename(os.path.dirname(url)) != WDS_DIR:
        return ""
    return repair_hint(os.path.dirname(os.path.dirname(url)) or ".")


def decode_wds_sample(sample: dict[str, Any], jacobian: bool = True, resolution: int | None = None) -> dict[str, Any]:
    """Decode a raw webdataset sample (bytes per member) into arrays; RispError naming shard and key.

    Returns ``dict(key, image (H,W,3) float32, jacobian (K,H,W,3) float32 or None, state (S,) float64,
    psi (K,) float64, meta dict)``.  Every member's checksum is verified; with ``jacobian=False`` the
    Jacobian EXR (the bulk of a sample) is not decoded and ``jacobian`` is None; with ``resolution`` (the
    manifest's) an EXR of another size is refused from its header, before its pixels are decoded.
    """
    for ext in ("image.exr", "json", "psi.npy", "state.npy"):
        if ext not in sample:
            raise RispError(f"corrupt or truncated webdataset sample ({_where(sample)}): missing member {ext}")
    try:
        meta = json.loads(sample["json"])
        sums = meta.pop("member_sha256", {})
        for ext, digest in sorted(sums.items()):
            if ext not in sample:
                raise ValueError(f"missing member {ext}")
            if hashlib.sha256(sample[ext]).hexdigest() != digest:
                raise ValueError(f"member {ext} does not match its sha256")
        image = decode_exr(sample["image.exr"], resolution)["RGB"]
        state = np.load(io.BytesIO(sample["state.npy"]), allow_pickle=False)
        psi = np.load(io.BytesIO(sample["psi.npy"]), allow_pickle=False)
        jac = None
        if jacobian and "jacobian.exr" in sample:
            jac = decode_jacobian(sample["jacobian.exr"], list(meta["psi_names"]), meta.get("jacobian_channels"),
                                  resolution)
        if state.shape != (len(meta["state_names"]),) or psi.shape != (len(meta["psi_names"]),):
            raise ValueError(f"state/psi shapes {state.shape}/{psi.shape} disagree with the names in its json")
    except (RispError, MemoryError):  # MemoryError: the machine's, not the bytes' (cli_util says it)
        raise
    except Exception as e:  # OpenEXR, numpy and json raise many types on corrupt bytes
        raise RispError(f"corrupt webdataset sample ({_where(sample)}): {type(e).__name__}: {e}"
                        f"{_repair(sample)}") from None
    return {
        "key": sample.get("__key__", ""),
        "image": image,
        "jacobian": jac,
        "state": state.astype(np.float64, copy=False),
        "psi": psi.astype(np.float64, copy=False),
        "meta": meta,
    }


def wds_urls(folder: str) -> list[str]:
    """Paths of the complete tar shards listed in the manifest, in shard order.

    Each listed file must exist with the size the manifest records (a cheap truncation check; use
    :func:`risp_data.shards.verify_checksums` for the full sha256 check).
    """
    m = load_manifest(folder)
    if "wds" not in m["formats"]:
        raise RispError(f"shard folder {folder} holds no webdataset shards (formats: {', '.join(m['formats'])})")
    urls = []
    for rec in m["shards"]:
        for rel, info in rec["files"].items():
            if not rel.startswith(WDS_DIR + "/"):
                continue
            path = os.path.join(folder, rel)
            if not os.path.exists(path):
                raise RispError(f"webdataset shard missing: {path}{repair_hint(folder)}")
            if os.path.getsize(path) != info["bytes"]:
                raise RispError(f"truncated or corrupt webdataset shard {path}: size differs from the manifest"
                                f"{repair_hint(folder)}")
            urls.append(path)
    return urls


def raise_with_url(exn: Exception) -> bool:
    """webdataset handler: turn a tar-level failure into one RispError naming the shard file (out of memory is the
    machine's, not the file's: raised as it is, for the command's own line)."""
    if isinstance(exn, (RispError, MemoryError)):
        raise exn
    url = next((a for a in reversed(getattr(exn, "args", ())) if isinstance(a, str) and a.endswith(".tar")), None)
    msg = str(exn.args[0]) if getattr(exn, "args", None) else type(exn).__name__
    raise RispError(f"corrupt or truncated webdataset shard {url or '<unknown>'}: {msg}") from None


class ShardCheck:
    """What each listed tar must hold: ``expected[path] = (start, stop)`` (its global sample indices) and the
    manifest's environment.  :meth:`samples` is a webdataset pipeline stage that expands shard urls into raw
    samples (like ``wds.tarfile_to_samples``) and stops with one RispError naming the shard when a shard
    yields a sample outside its range or of another environment, or fewer/more samples than the manifest
    lists — a tar whose tail a crash zero-filled reads as a valid, shorter archive otherwise."""

    def __init__(self, expected: dict[str, tuple[int, int]], env: str, handler=None):
        self.expected = {os.path.normpath(u): r for u, r in expected.items()}
        self.env, self.handler = env, handler or raise_with_url

    def _check_sample(self, url: str, raw: dict[str, Any]) -> None:
        start, stop = self.expected[os.path.normpath(url)]
        key = str(raw.get("__key__", ""))
        index = int(key[1:]) if key[:1] == "s" and key[1:].isdigit() else -1
        if not start <= index < stop:
            raise RispError(f"webdataset shard {url} holds sample {key!r}, outside its samples [{start}, {stop}) "
                            "in the manifest (a tar from another folder?)")
        try:
            env = json.loads(raw["json"]).get("env")
        except (KeyError, ValueError, AttributeError):
            return  # decode_wds_sample names the missing or corrupt member
        if env != self.env:
            raise RispError(f"webdataset shard {url} holds {env!r} samples, the folder's manifest says "
                            f"{self.env!r} (a tar from another folder?)")

    def samples(self, src: Iterator[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        import webdataset as wds

        expand = wds.tarfile_to_samples(handler=self.handler)
        for shard in src:
            url = shard["url"]
            if os.path.normpath(url) not in self.expected:
                raise RispError(f"webdataset shard {url} is not listed in its folder's manifest")
            start, stop = self.expected[os.path.normpath(url)]
            n = 0
            for raw in expand(iter([shard])):
                self._check_sample(url, raw)
                n += 1
                yield raw
            if n != stop - start:
                raise RispError(f"webdataset shard {url} holds {n} samples, the manifest lists {stop - start} "
                                "(truncated or damaged: rerun the render command or risp-data verify --repair)")


def shard_check(folder: str) -> ShardCheck:
    """The :class:`ShardCheck` of the complete tars of ``folder`` (paths as :func:`wds_urls` gives them)."""
    m = load_manifest(folder)
    expected = {os.path.join(folder, rel): (rec["start"], rec["stop"])
                for rec in m["shards"] for rel in rec["files"] if rel.startswith(WDS_DIR + "/")}
    return ShardCheck(expected, m["env"])


def shard_check_for_urls(urls: list[str], handler=None) -> ShardCheck:
    """One :class:`ShardCheck` over tars of one or more folders (``<folder>/wds/shard-NNNNNN.tar``)."""
    checks = [shard_check(f) for f in sorted({os.path.dirname(os.path.dirname(u)) for u in urls})]
    envs = {c.env for c in checks}
    if len(envs) > 1:
        raise RispError(f"shards of several environments cannot be read together: {', '.join(sorted(envs))}")
    expected = {u: r for c in checks for u, r in c.expected.items()}
    return ShardCheck(expected, checks[0].env if checks else "", handler)


def iter_wds(folder: str) -> Iterator[dict[str, Any]]:
    """Decoded samples of all complete shards, in index order, each shard checked against the manifest
    (:class:`ShardCheck`)."""
    import webdataset as wds

    urls = wds_urls(folder)
    if not urls:
        return iter(())
    resolution = load_manifest(folder).get("resolution")  # checked before each image is decoded
    pipeline = wds.DataPipeline(wds.SimpleShardList(urls), shard_check(folder).samples,
                                wds.map(functools.partial(decode_wds_sample, resolution=resolution),
                                        handler=raise_with_url))
    return iter(pipeline)
