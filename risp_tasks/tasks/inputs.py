"""Reading a task's inputs: the model (or the most recent run), the reference video, the actions CSV, the
camera JSON and the ground-truth JSON.  Every problem is one RispError line naming the file."""

from __future__ import annotations

import csv
import glob
import json
import math
import os
from dataclasses import dataclass

import numpy as np

from risp_data.envs import Camera
from risp_data.errors import RispError
from risp_data.numbers import is_finite_number

from ..video import Video, read_video, sha256_file

CAMERA_KEYS = {"intrinsics": ("width", "height", "fx"), "extrinsics": ("origin", "target", "up")}
#: the keys a camera JSON may hold besides CAMERA_KEYS
CAMERA_OPTIONAL = {"intrinsics": ("fy", "cx", "cy", "distortion"), "extrinsics": ()}
#: keys that carry geometry this camera model does not use (a rotation matrix, distortion terms, skew, a field of
#: view): refused, since ignoring them would render another camera than the file describes; other unknown keys
#: (a name, a model string) are listed in the result's warnings
CAMERA_GEOMETRY = {"rotation", "r", "rvec", "t", "tvec", "translation", "quaternion", "q", "position", "matrix", "k",
                   "k1", "k2", "k3", "k4", "p1", "p2", "skew", "fov", "fovx", "fovy", "fov_deg", "dist",
                   "dist_coeffs", "distortion_coefficients", "extrinsic_matrix", "intrinsic_matrix", "pose"}


def models_newest_first(runs: str = "runs") -> list[str]:
    """The ``model.pt`` files under ``runs/`` (one level of run folders), most recently written first (ties in path
    order, not the file system's listing order); RispError when there is none."""
    if not os.path.isdir(runs):
        raise RispError(f"no folder {runs}/ here to look for a trained model in: train one with `risp-train fit "
                        f"SHARDS` (it writes runs/…), pass --runs FOLDER or --model M")
    found = glob.glob(os.path.join(runs, "*", "model.pt")) + glob.glob(os.path.join(runs, "model.pt"))
    if not found:
        raise RispError(f"no trained model under {runs}/ (looked for {runs}/*/model.pt); train one with "
                        "`risp-train fit SHARDS` (it writes runs/…) or pass --model")
    return sorted(found, key=lambda p: (os.path.getmtime(p), p), reverse=True)


def model_env(path: str) -> str | None:
    """The environment a checkpoint was trained for, from its run's config.json (cheap) or the checkpoint; None when
    neither can be read (the caller's own load then reports the file)."""
    try:
        with open(os.path.join(os.path.dirname(path), "config.json")) as fh:
            env = json.load(fh).get("env")
        if isinstance(env, str):
            return env
    except (OSError, ValueError, AttributeError):
        pass
    from risp_train.checkpoint import load_checkpoint

    try:
        env = load_checkpoint(path).get("env")
    except RispError:  # unreadable or not a risp checkpoint: not this system's
        return None
    return env if isinstance(env, str) else None


def load_model(path: str, env: str | None):
    """A frozen predictor; RispError naming ``path`` when its environment is not ``env``, or its state and target
    names are not its environment's as risp defines it now (a model of an unknown system, or of another state
    layout: its readings would be taken for states they are not, or fail deep inside a task)."""
    from risp_data.envs import ENV_NAMES, get_environment
    from risp_train.checkpoint import check_compatible, read_checkpoint
    from risp_train.predictor import predictor_from_checkpoint

    ckpt, sha = read_checkpoint(path)
    trained_for = ckpt["env"]
    if env is not None and trained_for != env:
        raise RispError(f"{path}: the model was trained for environment {trained_for!r}, not {env!r}")
    if trained_for not in ENV_NAMES:
        raise RispError(f"{path}: the model was trained for environment {trained_for!r}, which risp does not know "
                        f"(it knows: {', '.join(ENV_NAMES)})")
    expected = get_environment(trained_for)
    check_compatible(ckpt, path, env=trained_for, state_names=expected.state_names)  # the state layout
    if list(ckpt["target_names"]) != list(expected.target_names):  # what the network outputs (check_compatible: states)
        raise RispError(f"checkpoint {path}: target names {list(ckpt['target_names'])} differ from the "
                        f"{trained_for}'s {list(expected.target_names)} (a model of another state layout: retrain it)")
    predictor = predictor_from_checkpoint(ckpt, path)
    predictor.sha256 = sha  # of the bytes loaded (risp_train.predictor.load)
    return predictor


def look_note(predictor, path: str, loss: str, mesh: str | None) -> str | None:
    """A warning line when the render loss would feed N images of another look than it was trained on: risp
    changed the environment's appearance since (risp_data.envs.look), and N has never seen the new marks."""
    from risp_data.envs.look import look_fingerprint

    if loss != "render" or mesh is not None:  # other losses do not feed N rendered images; a --mesh is the user's
        return None
    now = look_fingerprint(predictor.env_name)
    if predictor.look == now:
        return None
    return (f"note: {path} was trained on {predictor.env_name} images of another look ({predictor.look or 'unrecorded'}) "
            f"than risp renders now ({now}); the render loss compares N's readings of unlike images: retrain on new data "
            "(docs/environments.md §Appearance)")


def _unchanged_sha256(path: str, before: str | None) -> str:
    now = sha256_file(path)
    if before is not None and now != before:
        raise RispError(f"{path}: the video changed while it was read (another process replaced it); run again")
    return now


@dataclass(frozen=True)
class Reference:
    """The reference video at the network's resolution and the simulation timeline it lies on."""

    video: Video
    sha256: str
    source_fps: float  # frame rate of the decoded file (the simulation runs on this timeline)

    @property
    def indices(self) -> list[int]:
        return list(self.video.indices)

    @property
    def n_source(self) -> int:
        return self.video.source_frames


def read_reference(path: str, resolution: int, every: int, fps: float | None, source_fps: float | None) -> Reference:
    try:
        before = sha256_file(path)
    except (OSError, RispError):  # read_video says what is wrong with a bad path, in its own words
        before = None
    video = read_video(path, resolution=resolution, every=every, fps=fps, source_fps=source_fps)
    rate = video.source_fps
    if not rate > 0:
        raise RispError(f"{path}: the frame rate is unknown (a PNG folder or a still image): give --source-fps")
    # hashed before and after the decode: the checksum a result records must be of the frames it used (a
    # make-video --overwrite may rename another video into the path meanwhile)
    return Reference(video=video, sha256=_unchanged_sha256(path, before), source_fps=rate)


def action_columns(env: str) -> tuple[str, ...]:
    """Columns of an actions CSV after ``t``: quadrotor thrusts f0..f3 [N] (as docs/measured-data.md),
    hand u0..u4 [N·m], rod u0 [N]; the cube has none."""
    return {"quadrotor": ("f0", "f1", "f2", "f3"), "hand": tuple(f"u{i}" for i in range(5)), "rod": ("u0",)}.get(env, ())


def read_actions(path: str, env: str, n_frames: int, fps: float | None = None, timeline: str = "") -> np.ndarray:
    """(n_frames, A) actions in the CSV's units, one row per frame of the video's timeline.  With ``fps``, a numeric
    ``t`` column (optional; make-video writes k/fps) must follow that timeline: its steps within [0.5, 1.5]/fps (a
    row missing is a double step) and its mean step within 1 % of 1/fps (a file written at another rate) —
    otherwise the commands would be applied at the wrong frames.  A ``t`` that is not numbers (clock times) is not
    checked."""
    cols = action_columns(env)
    if not cols:
        raise RispError(f"{path}: the {env} has no actions")
    if os.path.isdir(path):
        raise RispError(f"{path}: a folder, not an actions file")
    if not os.path.isfile(path):
        raise RispError(f"{path}: actions file not found")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:  # -sig: a spreadsheet's byte-order mark is no column
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as e:
        raise RispError(f"{path}: cannot read actions CSV ({type(e).__name__})") from None
    except csv.Error as e:  # a field over the csv module's limit (an unclosed quote in a large file), a NUL in a quote
        raise RispError(f"{path}: not a readable actions CSV ({e})") from None
    if not rows:
        raise RispError(f"{path}: empty actions file")
    header = [h.strip() for h in rows[0]]
    if "" in header:  # a trailing comma, or two columns without names
        raise RispError(f"{path}: header column {header.index('') + 1} has no name (a trailing comma?); the {env}'s "
                        f"actions file has columns t,{','.join(cols)}")
    twice = sorted({h for h in header if header.count(h) > 1})
    if twice:  # which of the two is meant cannot be told: the first was taken without a word
        raise RispError(f"{path}: column {twice[0]} appears {header.count(twice[0])} times in the header")
    missing = [c for c in cols if c not in header]
    if missing:
        raise RispError(f"{path}: actions file for {env} needs columns t,{','.join(cols)}; missing {','.join(missing)} "
                        f"(has {len(header)} columns: {','.join(header)})")
    extra = [h for h in header if h not in ("t",) + tuple(cols)]
    if extra:  # e.g. a fifth motor: the file is for another system, or a column is misnamed
        raise RispError(f"{path}: unexpected column(s) {','.join(extra)}; the {env}'s actions file has columns "
                        f"t,{','.join(cols)}")
    idx = [header.index(c) for c in cols]
    t_col = header.index("t") if "t" in header else None
    data, times, lines = [], [], []
    for i, row in enumerate(rows[1:], start=2):
        if not row:  # a blank line (a trailing newline too many): no row
            continue
        if len(row) != len(header):
            raise RispError(f"{path}: line {i} has {len(row)} fields, header has {len(header)}")
        try:
            data.append([float(row[j]) for j in idx])
        except ValueError:
            raise RispError(f"{path}: line {i} has a non-numeric action") from None
        times.append(row[t_col] if t_col is not None else "")
        lines.append(i)
    a = np.asarray(data, np.float64).reshape(-1, len(cols))
    bad = ~np.isfinite(a)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise RispError(f"{path}: column {cols[c]} has NaN/inf at line {lines[r]}")
    if len(a) != n_frames:
        raise RispError(f"{path}: {len(a)} action rows but the video has {n_frames} frames{timeline} (one row per frame)")
    if t_col is not None and fps is not None and len(a) > 1:
        _check_times(path, times, lines, fps)
    return a


def _check_times(path: str, times: list[str], lines: list[int], fps: float) -> None:
    """The t column against a timeline of 1/fps steps (read_actions); not checked when t is not all numbers."""
    try:
        t = np.asarray([float(v) for v in times], np.float64)
    except ValueError:
        return
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:  # numbers, but NaN/inf: not clock times, a damaged column
        raise RispError(f"{path}: column t has NaN/inf at line {lines[int(bad[0])]}")
    steps = np.diff(t) * fps  # in frames: 1 on the video's timeline
    off = np.flatnonzero((steps < 0.5) | (steps > 1.5))
    if off.size:
        k = int(off[0]) + 1
        raise RispError(f"{path}: t steps from {t[k - 1]:g} to {t[k]:g} s at line {lines[k]} ({steps[k - 1]:.3g} frames "
                        f"of the video's {fps:g} fps; one row per frame, in order)")
    rate = (len(t) - 1) / (t[-1] - t[0])
    if abs(rate / fps - 1) > 0.01:
        raise RispError(f"{path}: t advances at {rate:.4g} rows per second, the video at {fps:g} frames per second "
                        f"(one row per frame of the video's timeline)")


def write_actions(path: str, env: str, actions: np.ndarray, fps: float) -> None:
    from risp_data.atomic import atomic_write

    cols = action_columns(env)
    with atomic_write(path, "w") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(("t",) + cols)
        for i, row in enumerate(np.asarray(actions)):
            w.writerow([f"{i / fps:.6f}"] + [f"{v:.9g}" for v in row])


def read_json(path: str, what: str) -> dict:
    if os.path.isdir(path):
        raise RispError(f"{path}: a folder, not a {what} file")
    if not os.path.isfile(path):
        raise RispError(f"{path}: {what} file not found")
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, ValueError) as e:
        raise RispError(f"{path}: not valid JSON ({type(e).__name__}: {str(e).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise RispError(f"{path}: {what} must be a JSON object")
    return data


MAX_FOV_DEG = 170.0  # beyond this a pinhole's image is all border: fx is almost surely in the wrong unit


def read_camera(path: str, video_size: tuple[int, int] | None = None, notes: list | None = None) -> Camera:
    """Camera JSON (docs/tasks.md §Camera): pinhole intrinsics (square pixels, principal point at the centre)
    and look-at extrinsics in the world frame (metres, z up).  Videos are centre-cropped to a square of side
    min(width, height), so the field of view the renderer uses is that square's: 2·atan(min(width, height) / 2fx).
    ``video_size`` (width, height of the decoded frames): the camera's must have its aspect ratio (within 1 %) unless
    the video is square (then it is the camera's centre square).  ``notes`` receives the unknown keys not used."""
    data = read_json(path, "camera")
    for group, keys in CAMERA_KEYS.items():
        if not isinstance(data.get(group), dict):
            raise RispError(f"{path}: camera JSON is missing the key {group!r} (an object with {', '.join(keys)})")
        missing = [k for k in keys if k not in data[group]]
        if missing:
            raise RispError(f"{path}: camera JSON is missing {', '.join(f'{group}.{k}' for k in missing)}")
    intr, extr = data["intrinsics"], data["extrinsics"]
    for group, keys in CAMERA_KEYS.items():
        unknown = sorted(set(data[group]) - set(keys) - set(CAMERA_OPTIONAL[group]))
        geometry = [k for k in unknown if k.lower() in CAMERA_GEOMETRY]
        if geometry:
            raise RispError(f"{path}: camera JSON key {group}.{geometry[0]} is not part of the camera model (pinhole, "
                            f"square pixels, no distortion; look-at extrinsics origin/target/up): remove it")
        if unknown and notes is not None:
            notes.append(f"{path}: camera key(s) {', '.join(f'{group}.{k}' for k in unknown)} not used")

    def number(value):
        if isinstance(value, (bool, str)):  # float(True) is 1.0, float("640") 640: a JSON true or string is no size
            raise TypeError
        return float(value)

    try:
        width, height, fx = (number(intr[k]) for k in ("width", "height", "fx"))
        centre = {k: number(intr[k]) for k in ("cx", "cy") if k in intr}
        fy = number(intr["fy"]) if "fy" in intr else None
        distortion = [number(v) for v in intr.get("distortion") or []]
        vecs = {k: np.array([number(v) for v in extr[k]]) for k in ("origin", "target", "up")}
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer literal beyond float's range
        raise RispError(f"{path}: camera values must be numbers, not strings or true/false (width, height, fx, fy, cx, "
                        "cy; origin/target/up: 3 numbers each)") from None
    if fy is not None and not abs(fy - fx) <= 0.01 * abs(fx):
        raise RispError(f"{path}: intrinsics.fy = {fy:g} differs from fx = {fx:g}: only square pixels are supported "
                        "(resample the video so that fx = fy)")
    if any(v != 0 for v in distortion):
        raise RispError(f"{path}: intrinsics.distortion {distortion} is not zero: lens distortion is not modelled "
                        "(undistort the video first)")
    if not all(math.isfinite(v) and v > 0 for v in (width, height, fx)):
        raise RispError(f"{path}: camera needs finite width, height and fx > 0, got {width:g}, {height:g}, {fx:g}")
    if any(len(v) != 3 or not np.all(np.isfinite(v)) for v in vecs.values()):
        raise RispError(f"{path}: camera needs finite 3-vectors origin, target, up")
    for key, half in (("cx", width / 2), ("cy", height / 2)):
        if key in centre and abs(centre[key] - half) > 0.01 * min(width, height) + 0.5:
            raise RispError(f"{path}: intrinsics.{key} = {centre[key]:g} is off the image centre ({half:g}): only a "
                            "centred principal point is supported (crop the video around it)")
    view = vecs["target"] - vecs["origin"]
    if np.linalg.norm(view) == 0:
        raise RispError(f"{path}: camera origin and target coincide")
    up = vecs["up"]
    if np.linalg.norm(np.cross(view, up)) <= 1e-6 * np.linalg.norm(view) * max(np.linalg.norm(up), 1e-300):
        raise RispError(f"{path}: camera 'up' {up.tolist()} is zero or parallel to the viewing direction "
                        f"(target − origin = {view.tolist()}): the image's roll is undefined")
    fov = math.degrees(2 * math.atan(min(width, height) / (2 * fx)))
    if fov >= MAX_FOV_DEG:
        raise RispError(f"{path}: fx = {fx:g} pixels for a {min(width, height):g}-pixel square gives a {fov:.1f}° "
                        f"field of view (at most {MAX_FOV_DEG:g}°): fx is in pixels of the same image as width")
    # a square video is the camera's centre square already (make-video --camera writes such frames): any aspect fits
    if (video_size is not None and video_size[0] != video_size[1]
            and abs(width / height - video_size[0] / video_size[1]) > 0.01 * width / height):
        raise RispError(f"{path}: a {width:g}×{height:g} camera, but the video's frames are {video_size[0]}×"
                        f"{video_size[1]} pixels (another aspect ratio): give the intrinsics of the camera that "
                        "filmed this video")
    return Camera(origin=tuple(vecs["origin"].tolist()), target=tuple(vecs["target"].tolist()),
                  up=tuple(up.tolist()), fov=fov)


def render_environment(env: str, mesh: str | None):
    """The environment the renderer draws: ``env`` itself, or with ``--mesh`` the quadrotor with the vehicle mesh
    from the file (docs/tasks.md §Vehicle mesh; only the quadrotor takes one)."""
    from risp_data.envs import get_environment

    if mesh is None:
        return get_environment(env)
    if env != "quadrotor":
        raise RispError(f"{mesh}: --mesh replaces the quadrotor's vehicle mesh; the {env} takes none")
    from risp_data.envs.quadrotor import make_environment

    return make_environment(mesh)


def read_truth(path: str, env: str | None = None, width: int | None = None, hint: str = "") -> dict:
    """make-video's ground truth (docs/tasks.md §Reference videos), checked before any work is done: of ``env``'s
    video (when it names one), with ``env_states`` a non-empty table of finite numbers with ``width`` columns (the
    environment's state size).  ``hint`` ends the wrong-environment line."""
    data = read_json(path, "ground-truth")
    if not isinstance(data, dict) or "env_states" not in data:
        raise RispError(f"{path}: ground-truth JSON is missing the key 'env_states'")
    if env is not None and data.get("env") not in (None, env):
        raise RispError(f"{path}: ground truth of a {data['env']} video, but the model is a {env} model{hint}")
    rows = data["env_states"]
    if not isinstance(rows, list) or not rows:
        raise RispError(f"{path}: 'env_states' must be a non-empty list of state rows")
    try:
        table = np.asarray(rows, np.float64)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer literal beyond float's range
        raise RispError(f"{path}: 'env_states' is not a table of numbers (rows of different lengths?)") from None
    if table.ndim != 2 or (width is not None and table.shape[1] != width):
        raise RispError(f"{path}: 'env_states' must have {width if width is not None else 'the same number of'} "
                        f"columns per row, got shape {table.shape}")
    if not np.all(np.isfinite(table)):
        raise RispError(f"{path}: 'env_states' holds NaN or inf")
    if "params" in data:  # the hidden parameters the errors are measured against: {name: finite number}
        params = data["params"]
        if not isinstance(params, dict) or not all(isinstance(k, str) and is_finite_number(v) for k, v in params.items()):
            raise RispError(f"{path}: 'params' must be an object of finite numbers, e.g. {{\"mass\": 3.0}}, "
                            f"got {json.dumps(params)[:40]}")
    return data

