"""The shard folder's manifest (``manifest.json``) and per-shard completion markers.

Completion protocol (docs/formats.md, "Completion and resume"):

1. The parent writes ``manifest.json`` before any shard is rendered; it fixes the folder's identity
   (environment, domain, resolution, spp, variant, Jacobian on/off, n, shard size, seed, formats).
2. A worker renders one shard (a contiguous range of sample indices), writes its tar under a temporary
   name and renames it, writes its zarr shard files, hashes every file, and only then writes the marker
   ``complete/shard-NNNNNN.json`` (again temp name + rename).
3. The parent adds the shard's record (files, sha256, sizes) to ``manifest.json`` (temp name + rename).

Readers trust only shards listed in the manifest; a shard without a marker does not exist.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import shlex
from importlib import metadata as _md
from typing import Any

from ..errors import RispError
from ..numbers import is_finite_number
from ..atomic import atomic_write

MANIFEST = "manifest.json"
MARKER_DIR = "complete"
FORMAT_NAME = "risp-shards"
FORMAT_VERSION = 2  # 2: jacobian_storage (own-channel Jacobians); folders of version 1 store J in full
# Fields that define what a folder holds; resuming with any of them different is refused.
IDENTITY_FIELDS = (
    "env",
    "look",  # risp_data.envs.look: a folder rendered with another appearance of the environment is not resumed
    "domain",
    "resolution",
    "spp",
    "variant",
    "jacobian",
    "n",
    "shard_size",
    "seed",
    "formats",
)
_VERSION_PACKAGES = {
    "risp": "risp",
    "mitsuba": "mitsuba",
    "drjit": "drjit",
    "torch": "torch",
    "numpy": "numpy",
    "zarr": "zarr",
    "webdataset": "webdataset",
    "OpenEXR": "OpenEXR",
}


def package_versions() -> dict[str, str | None]:
    """Installed versions of the packages that shape the samples (None when not installed)."""
    out: dict[str, str | None] = {}
    for label, dist in _VERSION_PACKAGES.items():
        try:
            out[label] = _md.version(dist)
        except _md.PackageNotFoundError:
            out[label] = None
    return out


def risp_commit() -> str | None:
    """The git commit of the risp checkout this code runs from (None outside a git checkout, e.g. a wheel)."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        return subprocess.run(["git", "-C", root, "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=5).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def sha256_file(path: str, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            block = f.read(chunk)
            if not block:
                break
            h.update(block)
    return h.hexdigest()


def file_record(folder: str, rel: str) -> dict[str, Any]:
    """``{"sha256": ..., "bytes": ...}`` of ``folder/rel``."""
    path = os.path.join(folder, rel)
    return {"sha256": sha256_file(path), "bytes": os.path.getsize(path)}


def write_json_atomic(path: str, obj: Any) -> None:
    """Write JSON to a temporary file in the same folder, fsync it, then rename over ``path``."""
    with atomic_write(path, "w", suffix=".json") as f:
        json.dump(obj, f, indent=1, sort_keys=True, allow_nan=False)
        f.write("\n")


def _read_json(path: str, what: str) -> dict[str, Any]:
    try:
        with open(path) as f:
            obj = json.load(f)
    except FileNotFoundError:
        raise RispError(f"{what} not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise RispError(f"corrupt {what} {path}: {e}") from None
    if not isinstance(obj, dict):
        raise RispError(f"corrupt {what} {path}: expected a JSON object")
    return obj


def datasets_in(folder: str) -> list[str]:
    """The subfolders of ``folder`` that hold a manifest.json (its data sets), as paths, sorted."""
    try:
        names = sorted(os.listdir(folder))
    except OSError:
        return []
    return [os.path.join(folder, n) for n in names if os.path.isfile(os.path.join(folder, n, MANIFEST))]


def load_manifest(folder: str) -> dict[str, Any]:
    """Read ``folder/manifest.json``; RispError when it is missing, corrupt or not a risp shard manifest."""
    path = os.path.join(folder, MANIFEST)
    if os.path.isfile(folder):  # e.g. a video given to `risp-data inspect`
        raise RispError(f"{folder} is a file, not a shard folder (give the folder risp-data render wrote)")
    if not os.path.isdir(folder):
        raise RispError(f"shard folder not found: {folder}")
    if not os.path.exists(path):
        inside = datasets_in(folder)
        if inside:  # a parent folder (e.g. the default shards/) given where one data set is meant: name them
            raise RispError(f"{folder} is not a data set but holds {len(inside)}: {', '.join(inside)}; "
                            "pass one of them")
    m = _read_json(path, "manifest")
    if m.get("format") != FORMAT_NAME:
        raise RispError(f"corrupt manifest {path}: not a {FORMAT_NAME} manifest")
    # "look" came later: folders rendered before it still read (and train); only resuming them is refused
    missing = [k for k in (*IDENTITY_FIELDS, "psi", "state_names", "shards") if k not in m and k != "look"]
    if missing:
        raise RispError(f"corrupt manifest {path}: missing field(s) {', '.join(missing)}")
    wrong = _wrong_types(m)
    if wrong:
        raise RispError(f"corrupt manifest {path}: {wrong}")
    if m.get("format_version", 0) > FORMAT_VERSION:
        raise RispError(
            f"manifest {path} has format_version {m['format_version']}; this risp reads <= {FORMAT_VERSION}"
        )
    return m


#: the manifest's fields that its readers compute with, and their JSON types (a hand-edited "n": "abc" must be one
#: line here, not a traceback wherever it is first used)
_INT_FIELDS = ("resolution", "spp", "n", "shard_size", "seed", "num_shards", "format_version")
_STR_FIELDS = ("env", "domain", "variant", "look")


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _wrong_types(m: dict[str, Any]) -> str | None:
    """The first field of ``m`` whose type is not the one risp writes (None when all are)."""
    for k in _INT_FIELDS:
        if k in m and not (_is_int(m[k]) and m[k] >= 0):
            return f"field {k} is not a non-negative integer ({m[k]!r})"
    for k in _STR_FIELDS:
        if k in m and not isinstance(m[k], str):
            return f"field {k} is not a string ({m[k]!r})"
    if not isinstance(m["jacobian"], bool):
        return f"field jacobian is not true or false ({m['jacobian']!r})"
    if not (isinstance(m["formats"], list) and all(isinstance(f, str) for f in m["formats"])):
        return "field formats is not a list of names"
    if not isinstance(m["psi"], dict) or not isinstance(m["state_names"], list):
        return "field psi is not an object" if not isinstance(m["psi"], dict) else "field state_names is not a list"
    if not all(isinstance(n, str) for n in m["state_names"]):
        return "field state_names is not a list of names"
    names = m["psi"].get("names")
    if not (isinstance(names, list) and names and all(isinstance(n, str) for n in names)):
        return "field psi.names is not a list of names"
    for k in ("low", "high", "nominal"):  # the ψ box: inspect prints it, verify steps through it
        v = m["psi"].get(k)
        if not (isinstance(v, list) and len(v) == len(names) and all(is_finite_number(x) for x in v)):
            return f"field psi.{k} is not a list of {len(names)} finite numbers (one per psi name)"
    if not _is_int(m.get("num_shards")):
        return "field num_shards is missing"
    if "resolution" in m and m["resolution"] > _MAX_RESOLUTION:
        return f"field resolution {m['resolution']} is larger than the supported {_MAX_RESOLUTION} pixels"
    for k, kind in (("counts", dict), ("versions", dict)):
        if k in m and not isinstance(m[k], kind):
            return f"field {k} is not an object"
    if "complete" in m and not isinstance(m["complete"], bool):
        return f"field complete is not true or false ({m['complete']!r})"
    if not isinstance(m["shards"], list):
        return "field shards is not a list"
    n = m.get("n")
    for rec in m["shards"]:
        if not (isinstance(rec, dict) and all(_is_int(rec.get(k)) for k in ("index", "start", "stop"))
                and isinstance(rec.get("files"), dict)
                and all(isinstance(f, dict) and _is_int(f.get("bytes")) and isinstance(f.get("sha256"), str)
                        for f in rec["files"].values())
                and 0 <= rec["start"] < rec["stop"] and (not _is_int(n) or rec["stop"] <= n)):
            return f"a record of field shards is malformed ({str(rec)[:60]})"
    return None


_MAX_RESOLUTION = 8192  # risp_data.generate.MAX_RESOLUTION (not imported: generate imports this module)



def save_manifest(folder: str, manifest: dict[str, Any]) -> None:
    manifest = dict(manifest)
    manifest["updated"] = utc_now()
    shards = sorted(manifest["shards"], key=lambda r: r["index"])
    manifest["shards"] = shards
    done = sum(r["stop"] - r["start"] for r in shards)
    manifest["counts"] = {
        "samples": manifest["n"],
        "shards": manifest["num_shards"],
        "complete_samples": done,
        "complete_shards": len(shards),
    }
    manifest["complete"] = len(shards) == manifest["num_shards"]
    write_json_atomic(os.path.join(folder, MANIFEST), manifest)


def identity_mismatch(existing: dict[str, Any], wanted: dict[str, Any]) -> list[str]:
    """Human-readable differences between two manifests' identity fields (empty when compatible)."""
    diffs = []
    for k in IDENTITY_FIELDS:
        a, b = existing.get(k), wanted.get(k)
        if isinstance(a, list):
            a = tuple(a)
        if isinstance(b, list):
            b = tuple(b)
        if a != b:
            diffs.append(f"{k}={existing.get(k)!r} (folder) vs {wanted.get(k)!r} (requested)")
    return diffs


def marker_path(folder: str, shard_index: int) -> str:
    return os.path.join(folder, MARKER_DIR, f"shard-{shard_index:06d}.json")


def write_marker(folder: str, record: dict[str, Any]) -> None:
    os.makedirs(os.path.join(folder, MARKER_DIR), exist_ok=True)
    write_json_atomic(marker_path(folder, record["index"]), record)


def read_marker(folder: str, shard_index: int) -> dict[str, Any] | None:
    """A shard's completion record, or None when there is none or it does not match the files on disk.

    Only sizes are compared here (cheap, used on resume); :func:`verify_checksums` hashes the files.
    """
    path = marker_path(folder, shard_index)
    if not os.path.exists(path):
        return None
    try:
        rec = _read_json(path, "shard marker")
        if not isinstance(rec, dict) or not isinstance(rec.get("files"), dict):  # a marker edited or left by hand
            return None
        for rel, info in rec["files"].items():
            if os.path.getsize(os.path.join(folder, rel)) != info["bytes"]:
                return None
    except (RispError, OSError, KeyError, TypeError, AttributeError):
        return None
    return rec


def file_problem(folder: str, rel: str, info: dict[str, Any], deep: bool) -> str | None:
    """Why shard file ``folder/rel`` is not the one its record lists (missing, other size, other sha256 when
    ``deep``), or None when it is."""
    path = os.path.join(folder, rel)
    try:
        size = os.path.getsize(path)
    except FileNotFoundError:
        return f"{path} is missing"
    if size != info["bytes"]:
        return f"{path} has {size} bytes, the manifest lists {info['bytes']}"
    if deep and sha256_file(path) != info["sha256"]:
        return f"{path}: sha256 differs from the manifest"
    return None


def shard_problem(folder: str, record: dict[str, Any], deep: bool = True) -> str | None:
    """The first problem of a listed shard's files (see :func:`file_problem`), or None when intact."""
    for rel, info in sorted(record["files"].items()):
        why = file_problem(folder, rel, info, deep)
        if why is not None:
            return why
    return None


def repair_hint(folder: str) -> str:
    """What every damaged-shard error ends with: the command that re-renders the damaged shards."""
    return f"; repair: risp-data verify --repair {shlex.quote(folder)}"  # quoted: copied into a shell as printed


def verify_checksums(folder: str, manifest: dict[str, Any] | None = None) -> int:
    """Hash every file of every complete shard and compare with the manifest; returns the number checked.

    Raises RispError naming the first missing, truncated or corrupt file.
    """
    m = load_manifest(folder) if manifest is None else manifest
    checked = 0
    for rec in m["shards"]:
        for rel, info in sorted(rec["files"].items()):
            path = os.path.join(folder, rel)
            if not os.path.exists(path):
                raise RispError(f"shard file missing: {path}{repair_hint(folder)}")
            size = os.path.getsize(path)
            if size != info["bytes"]:
                raise RispError(f"truncated or corrupt shard file {path}: {size} bytes, manifest says {info['bytes']}"
                                f"{repair_hint(folder)}")
            if sha256_file(path) != info["sha256"]:
                raise RispError(f"corrupt shard file {path}: sha256 differs from the manifest{repair_hint(folder)}")
            checked += 1
    return checked
