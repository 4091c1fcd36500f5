"""Checkpoints: one ``torch.save`` file of plain tensors, lists, dicts, strings and numbers.

Loaded with ``torch.load(path, weights_only=True)`` — no pickled objects.  Written atomically (temporary
file in the same folder, fsync, ``os.replace``), so a kill never leaves a half-written checkpoint.

Keys (docs/training.md §Checkpoints):

    format, format_version       "risp-train-checkpoint", 1
    env, state_names, target_names, psi_names, resolution
    manifest_hash, shards        the training shards (sha256 of their identity and file hashes; folder)
    look                         the training images' look (risp_data.envs.look; None for older data)
    seed, config, model_config   the run's TrainConfig and ModelConfig as dicts
    normalization                Normalization.to_dict()
    model                        the network's state_dict
    optimizer, scheduler         their state_dicts (training checkpoints only)
    progress                     epoch, batch (next batch within the epoch), global_step, total_steps, complete
    history                      per-epoch summaries (list of dicts)
    world_size, workers          data split of the run (a resumed run must use the same to replay the order)
"""

from __future__ import annotations

import os
from typing import Any

import torch

from risp_data.errors import RispError
from risp_data.atomic import atomic_write

FORMAT = "risp-train-checkpoint"
FORMAT_VERSION = 1
REQUIRED = ("env", "state_names", "target_names", "normalization", "model", "model_config", "resolution")


def plain(obj: Any) -> Any:
    """A copy of ``obj`` that ``torch.load(weights_only=True)`` accepts: tensors, dicts, lists, str, numbers."""
    if isinstance(obj, torch.Tensor):
        return obj
    if isinstance(obj, dict):
        return {plain(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, bool) or obj is None:
        return obj
    if isinstance(obj, str):
        return str(obj)  # also str subclasses such as torch.__version__
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return float(obj)
    if hasattr(obj, "item"):  # numpy scalars
        return obj.item()
    raise TypeError(f"cannot store {type(obj).__name__} in a weights-only checkpoint")


def save_checkpoint(path: str, payload: dict[str, Any]) -> None:
    """Atomically write ``payload`` (plus the format tags) to ``path``; RispError naming the file when the
    write fails (disk full: torch reports it as a RuntimeError of its zip writer); the old file is kept."""
    payload = plain({"format": FORMAT, "format_version": FORMAT_VERSION, **payload})
    try:
        with atomic_write(path, "wb", suffix=".pt") as f:
            torch.save(payload, f)
    except OSError as e:
        raise RispError(f"cannot write checkpoint {path}: {e.strerror or e}") from None
    except RuntimeError as e:  # torch's zip writer wraps the OSError of a failed write
        cause = e.__cause__ or e.__context__
        if not isinstance(cause, OSError) and "PytorchStreamWriter" not in str(e):
            raise
        reason = getattr(cause, "strerror", None) or "the write failed (disk full?)"
        raise RispError(f"cannot write checkpoint {path}: {reason}") from None


def _load_error(path: str, e: Exception) -> str:
    """One line for a checkpoint torch cannot read, without torch's advice to load it unsafely
    (``weights_only=False`` would execute whatever the file's pickle says)."""
    import re

    text = str(e)
    found = re.search(r"Unsupported global: GLOBAL (\S+)", text)
    if found:
        return (f"refused checkpoint {path}: it holds a pickled {found.group(1)} object; risp checkpoints hold "
                "only tensors and plain values (another program's file, or a malicious one)")
    detail = re.search(r"WeightsUnpickler error:\s*(\S[^\n]*)", text)
    first = detail.group(1) if detail else (text.splitlines()[0] if text else "")
    return f"corrupt or unreadable checkpoint {path}: {type(e).__name__}{': ' + first if first else ''}"


#: where ``risp-train fit --overwrite`` keeps the run it replaces until the new run has written its first checkpoint
SET_ASIDE = ".overwritten-run"


def model_file(path: str) -> str:
    """The checkpoint that ``path`` names: the file itself, or a run folder's ``model.pt`` (what
    ``risp-train fit --out FOLDER`` writes when training ends)."""
    if not os.path.isdir(path):
        return path
    found = os.path.join(path, "model.pt")
    if os.path.isfile(found):
        return found
    unfinished = os.path.isfile(os.path.join(path, "last.pt"))
    if not unfinished and os.path.isfile(os.path.join(path, SET_ASIDE, "model.pt")):  # fit --overwrite before its
        # first checkpoint: still running, or killed (SIGKILL, SIGTERM) — the earlier model waits in SET_ASIDE
        raise RispError(f"{path} has no model.pt: a risp-train fit --overwrite set the previous run aside in "
                        f"{os.path.join(path, SET_ASIDE)} and has written no checkpoint yet (it is still running, or "
                        f"was stopped); to use the previous model once no fit runs there, move that folder's files "
                        f"back into {path}")
    raise RispError(f"{path} is a folder without a model.pt" + (
        ": its training has not finished (last.pt is the resumable checkpoint; run the same fit again with --resume)"
        if unfinished else "; pass a risp-train checkpoint or a run folder that holds one"))


def load_checkpoint(path: str) -> dict[str, Any]:
    """Read a checkpoint (a file, or a run folder's model.pt) with ``weights_only=True``; RispError when
    missing, corrupt, not ours, or holding non-finite weights or a degenerate normalization
    (:func:`check_values`)."""
    return read_checkpoint(path)[0]


def read_checkpoint(path: str) -> tuple[dict[str, Any], str]:
    """:func:`load_checkpoint` and the sha256 of the very bytes it loaded: a result that names its model by
    checksum must name this one, not whatever file a later fit has renamed into the path since."""
    import hashlib
    import io

    path = model_file(path)
    if not os.path.isfile(path):
        raise RispError(f"checkpoint not found: {path}")
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise RispError(f"cannot read checkpoint {path}: {e.strerror or e}") from None
    if not data:
        raise RispError(f"corrupt checkpoint {path}: the file is empty (0 bytes)")
    _check_kind(path, data)
    try:
        ckpt = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as e:  # zipfile, unpickler and EOF errors on damaged files
        raise RispError(_load_error(path, e)) from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise RispError(f"{path} is not a risp-train checkpoint")
    if int(ckpt.get("format_version", 0)) > FORMAT_VERSION:
        raise RispError(f"checkpoint {path} has format_version {ckpt['format_version']}; this risp reads <= {FORMAT_VERSION}")
    missing = [k for k in REQUIRED if k not in ckpt]
    if missing:
        raise RispError(f"corrupt checkpoint {path}: missing {', '.join(missing)}")
    check_values(ckpt, path)
    check_consistent(ckpt, path)
    return ckpt, hashlib.sha256(data).hexdigest()


_ZIP, _PICKLE = b"PK\x03\x04", b"\x80"  # torch.save writes a zip archive; torch before 1.6 a bare pickle
#: first bytes of files that land where a checkpoint goes (an eval's plot, a shard, a rendered frame)
_KNOWN_KINDS = ((b"\x89PNG", "a PNG image"), (b"v/1\x01", "an OpenEXR image"), (b"\x1f\x8b", "a gzip file"))


def _check_kind(path: str, data: bytes) -> None:
    """Another kind of file given where a checkpoint goes: say what it is, instead of the unpickler's "KeyError:
    101" (a text file's first byte read as an opcode) or a zip reader's "file in archive is not in a subdirectory"."""
    if data.startswith(_ZIP):
        names = _zip_names(data)
        if names is not None and not any(n.endswith("/data.pkl") for n in names):  # None: damaged, torch says so
            raise RispError(f"corrupt or unreadable checkpoint {path}: a zip archive of {', '.join(names[:3]) or 'nothing'}"
                            " without torch's data.pkl (a .npz or another program's archive?), not a risp-train checkpoint")
        return
    if data.startswith(_PICKLE):
        return
    text = _as_text(data[:4096])
    if text is not None:
        first = text.strip().splitlines()[0][:40]
        raise RispError(f"{path} is a text file (it begins {first!r}), not a risp-train checkpoint; pass the model.pt "
                        "that risp-train fit wrote, or its run folder")
    kind = next((k for magic, k in _KNOWN_KINDS if data.startswith(magic)), None)
    if kind is None and data[257:262] == b"ustar":
        kind = "a tar archive"
    raise RispError(f"corrupt or unreadable checkpoint {path}: " + (f"{kind}, not a risp-train checkpoint" if kind else
                    f"not a torch.save file (it begins with bytes {data[:4].hex(' ')}, neither a zip archive nor a pickle)"))


def _zip_names(data: bytes) -> list[str] | None:
    """The member names of a zip archive's bytes; None when the archive cannot be read."""
    import io
    import zipfile

    try:
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            return z.namelist()
    except (zipfile.BadZipFile, OSError, ValueError):
        return None


def _as_text(head: bytes) -> str | None:
    """``head`` decoded when it is printable UTF-8 text (a character cut at its end allowed), else None."""
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as e:
        if e.start < len(head) - 3:  # not a multi-byte character cut by the 4 KiB sample: binary
            return None
        text = head[:e.start].decode("utf-8")
    if not text.strip() or any(c < " " and c not in "\t\n\r\f" for c in text):
        return None
    return text


def check_consistent(ckpt: dict[str, Any], path: str) -> None:
    """The checkpoint's parts must describe one network: T = len(target_names) normalization entries per target
    vector and 3 per image vector, a network with T outputs, and a resolution its stem takes.  A file edited by
    hand or assembled from two runs otherwise loads and fails at its first use with a shape error."""
    from .model import STEM_FACTOR, min_resolution

    n_targets = len(ckpt["target_names"])
    norm = ckpt["normalization"]
    for key, want, what in (("image_mean", 3, "3 colour channels"), ("image_std", 3, "3 colour channels"),
                            ("target_mean", n_targets, f"{n_targets} target_names"),
                            ("target_std", n_targets, f"{n_targets} target_names")):
        got = len(torch.as_tensor(norm[key]).reshape(-1))
        if got != want:
            raise RispError(f"inconsistent checkpoint {path}: normalization {key} has {got} entries, "
                            f"the checkpoint has {what}")
    if not ckpt["state_names"]:
        raise RispError(f"inconsistent checkpoint {path}: it names no state entries (state_names is empty)")
    config = ckpt["model_config"]
    if not isinstance(config, dict) or config.get("stem") not in STEM_FACTOR or "out_dim" not in config:
        raise RispError(f"corrupt checkpoint {path}: model_config {config!r} names no known stem and out_dim "
                        f"(stems: {', '.join(STEM_FACTOR)})")
    if int(config["out_dim"]) != n_targets:
        raise RispError(f"inconsistent checkpoint {path}: the network predicts {config['out_dim']} targets, "
                        f"the checkpoint has {n_targets} target_names")
    resolution, stem = ckpt["resolution"], config["stem"]
    if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < min_resolution(stem):
        raise RispError(f"inconsistent checkpoint {path}: resolution {resolution!r} does not suit its network "
                        f"(stem {stem!r} takes images of at least {min_resolution(stem)}×{min_resolution(stem)})")


def check_values(ckpt: dict[str, Any], path: str) -> None:
    """Weights and normalization must be usable: every floating tensor of the model finite, every image and
    target standard deviation finite and > 0 (a zero std divides the inputs by zero: NaN predictions)."""
    model = ckpt["model"]
    if not isinstance(model, dict):
        raise RispError(f"corrupt checkpoint {path}: 'model' is not a state dict")
    bad = [k for k, t in model.items()
           if isinstance(t, torch.Tensor) and t.is_floating_point() and not torch.isfinite(t).all()]
    if bad:
        raise RispError(f"checkpoint {path} holds non-finite (NaN/inf) weights in {', '.join(bad[:3])}"
                        f"{' …' if len(bad) > 3 else ''} (training diverged?)")
    norm = ckpt["normalization"]
    for key in ("image_std", "target_std", "image_mean", "target_mean"):
        values = norm.get(key) if isinstance(norm, dict) else None
        if values is None:
            raise RispError(f"corrupt checkpoint {path}: normalization lacks {key}")
        t = torch.as_tensor(values, dtype=torch.float64)
        if not torch.isfinite(t).all() or (key.endswith("_std") and not (t > 0).all()):
            raise RispError(f"checkpoint {path}: normalization {key} {t.tolist()} is not finite"
                            f"{' and > 0' if key.endswith('_std') else ''}")


def check_compatible(ckpt: dict[str, Any], path: str, *, env: str, state_names, resolution: int | None = None) -> None:
    """A checkpoint used with shards must be of the same environment, state vector and resolution."""
    if ckpt["env"] != env:
        raise RispError(f"checkpoint {path} was trained on environment {ckpt['env']!r}, not {env!r}")
    if list(ckpt["state_names"]) != list(state_names):
        raise RispError(f"checkpoint {path}: state names {list(ckpt['state_names'])} differ from {list(state_names)}")
    if resolution is not None and int(ckpt["resolution"]) != int(resolution):
        raise RispError(f"checkpoint {path} expects {ckpt['resolution']}×{ckpt['resolution']} images, "
                        f"the shards are {resolution}×{resolution}")
