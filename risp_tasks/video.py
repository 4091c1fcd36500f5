"""Video input and output (PyAV / FFmpeg): ``.mp4``, ``.avi``, ``.mov``, ``.mkv`` or a folder of PNGs.

Colour: files hold 8-bit sRGB; the network and the renderer work in linear RGB.  Reading applies the sRGB
EOTF (IEC 61966-2-1) and writing its inverse after clipping to [0, 1] (no other tone mapping), so a
rendered image written and read back differs only by 8-bit quantisation and codec loss.

Resizing to the network's resolution: a centre crop to a square, then area averaging in *linear* RGB
(torch ``interpolate(mode="area")`` for shrinking, bilinear for growing).  Temporal sampling: ``fps``
picks, for output time k / fps, the nearest input frame; then ``every`` keeps every k-th of those.
"""

from __future__ import annotations

import errno
import hashlib
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from risp_data.atomic import atomic_write
from risp_data.errors import RispError, message_line

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")
CODECS = {".mp4": "libx264", ".mkv": "libx264", ".mov": "libx264", ".avi": "mpeg4"}


@dataclass(frozen=True)
class Video:
    frames: np.ndarray  # (T, H, W, 3) float32 linear RGB
    fps: float  # frames per second of ``frames`` (after temporal sampling)
    source: str  # path it came from
    source_frames: int  # frames decoded from the file
    indices: tuple[int, ...]  # which decoded frames ``frames`` holds
    source_fps: float = 0.0  # frame rate of the decoded frames (0: unknown, a PNG folder without source_fps)
    comment: str = ""  # the file's comment tag ("" for a PNG folder): make-video writes MADE_BY there
    notes: tuple[str, ...] = ()  # what the reader did that the user should know (an overridden frame rate)
    source_size: tuple[int, int] | None = None  # (width, height) of the frames as decoded, before resizing


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


#: srgb_to_linear of every 8-bit value: a frame converts by table look-up, to the same bits as the formula.
SRGB8_TO_LINEAR = srgb_to_linear(np.arange(256, dtype=np.float32) / 255.0)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(np.asarray(x, np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055).astype(np.float32)


def to_uint8(linear: np.ndarray) -> np.ndarray:
    return np.round(linear_to_srgb(linear) * 255).astype(np.uint8)


def sha256_file(path: str | os.PathLike) -> str:
    """sha256 of a file (risp_data's, so checksums agree across packages), or of a folder's PNGs (names and
    contents, sorted)."""
    from risp_data.shards.manifest import sha256_file as file_sha256

    p = Path(path)
    if not p.is_dir():
        return file_sha256(str(p))
    h = hashlib.sha256()
    for f in png_frames(p):
        h.update(f.name.encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def _av():
    try:
        import av
    except ImportError:
        raise RispError("reading and writing videos needs PyAV: pip install av") from None
    return av


class _Converting(Exception):
    """An error of a frame's conversion (``each``), not of the decoder: re-raised as what it was."""


def _decode_file(path: Path, each=lambda img: img) -> tuple[list[np.ndarray], float, str, tuple | None, list[str]]:
    """(``each`` of every decoded (H, W, 3) uint8 frame, the stream's frame rate, the container's comment tag, the
    frames' (width, height) as decoded, notes on the timestamps)."""
    av = _av()
    first = None

    def convert(img: np.ndarray) -> np.ndarray:
        nonlocal first
        first = img.shape if first is None else first
        if img.shape != first:  # one size per video (a resized frame would hide the change)
            raise RispError(f"{path}: the frame size changes from {first[1]}×{first[0]} to {img.shape[1]}×{img.shape[0]} "
                            "pixels within the video")
        try:
            return each(img)
        except Exception as e:  # noqa: BLE001 - whatever the conversion raised, e.g. MemoryError
            raise _Converting() from e

    try:
        with av.open(str(path)) as container:
            streams = container.streams.video
            if not streams:
                raise RispError(f"{path}: not a video (no video stream)")
            stream = streams[0]
            _check_picture_codec(path, container, stream)
            rate = stream.average_rate or stream.base_rate or stream.guessed_rate
            frames, times, turns = [], [], set()
            for f in container.decode(stream):
                img, turn = _upright(path, f)
                turns.add(turn)
                frames.append(convert(img))
                times.append(None if f.pts is None or f.time_base is None else float(f.pts * f.time_base))
            comment = _comment(container)
            announced = _announced(container, stream)
    except RispError:
        raise
    except _Converting as e:
        raise e.__cause__ from None
    except Exception as e:  # noqa: BLE001 - PyAV raises many error types (InvalidDataError, …)
        raise RispError(f"{path}: cannot decode as a video ({_decoder_message(e)})") from None
    _check_complete(path, frames, times, announced)
    note = _check_constant_rate(path, times)
    notes = [note] if note else []
    if turns - {0}:
        said = {90: "90° counterclockwise", 180: "180°", 270: "90° clockwise"}
        notes.append(f"{path.name}: frames turned {', '.join(said[t] for t in sorted(turns - {0}))}, as its display "
                     "matrix says (a phone held upright or upside down)")
    return (frames, float(rate) if rate else 0.0, comment, (first[1], first[0]) if first else None, notes)


# FFmpeg's text-art demuxers (tty: ANSI art, also any plain text file of a few kB; bin, xbin, adf, idf) turn a
# file of text into a "video" of rendered characters; a task must not read a README as footage.
TEXT_ART_CODECS = frozenset({"ansi", "bintext", "xbin", "idf"})


def _check_picture_codec(path: Path, container, stream) -> None:
    """One line when FFmpeg decodes ``path`` only as text art (its codec renders characters), not as pictures."""
    codec = (stream.codec_context.name or "").lower()
    if codec in TEXT_ART_CODECS:
        raise RispError(f"{path}: not a video (FFmpeg reads it as text drawn as characters: format "
                        f"{container.format.name}, codec {codec})")


def _decoder_message(error: BaseException) -> str:
    """The decoder's own words for ``error``: PyAV's FFmpeg errors carry ``strerror`` (without the errno number
    that their str() starts with); other errors their type and first line."""
    said = getattr(error, "strerror", None)
    if isinstance(said, str) and said.strip():
        return said.strip()
    return f"{type(error).__name__}: {message_line(error)}"


def _display_matrix(frame) -> np.ndarray | None:
    """The frame's display matrix (9 int32: a b u / c d v / x y w, ffmpeg's DISPLAYMATRIX side data), or None."""
    try:
        data = frame.side_data.get("DISPLAYMATRIX")
    except (AttributeError, KeyError, TypeError, ValueError):
        return None
    if data is None:
        return None
    values = np.frombuffer(memoryview(data), dtype=np.int32)
    return values if values.size == 9 else None


def _upright(path: Path, frame) -> tuple[np.ndarray, int]:
    """A decoded frame as it is meant to be seen, and the turn applied (degrees counterclockwise, a multiple of 90):
    a phone held upright stores landscape frames and a display matrix turning them (PyAV's ``frame.rotation``; the
    rotation ffmpeg's own autorotate applies), which a reader must apply or the network sees the scene sideways."""
    img = frame.to_ndarray(format="rgb24")
    matrix = _display_matrix(frame)
    if matrix is None:
        return img, 0
    a, b, c, d = matrix[0], matrix[1], matrix[3], matrix[4]
    det = float(a) * d - float(b) * c
    if det == 0:  # degenerate (e.g. all zero): no transformation, as ffmpeg plays it
        return img, 0
    if det < 0:
        raise RispError(f"{path}: its display matrix mirrors the frames (a flip, which risp does not apply): "
                        "re-encode it as it is shown")
    rotation = float(frame.rotation)
    turns = round(rotation / 90.0)
    if abs(rotation - 90 * turns) > 1.0:
        raise RispError(f"{path}: its display matrix turns the frames by {rotation:g}°, not a multiple of 90°: "
                        "re-encode it upright")
    turn = (90 * turns) % 360
    return (np.ascontiguousarray(np.rot90(img, k=turns)) if turn else img), turn


def _announced(container, stream) -> tuple[int | None, float | None, bool, bool]:
    """(frame count, seconds, whether the seconds are an end time from 0 rather than a span, whether the count can
    be trusted) that the header announces for the video stream; None for what it does not say.  The seconds are
    the video stream's own — its duration (a span), or a Matroska track's DURATION tag (an end time) — and the
    container's (an end time) only when it holds no other stream (an audio track may run longer than the picture).
    The count is not trusted in MP4/MOV, whose edit lists (a stream-copied trim) announce frames the decoder drops."""
    seconds, end_time = None, False
    if stream.duration and stream.time_base:
        seconds = float(stream.duration * stream.time_base)
    elif stream.metadata.get("DURATION"):  # Matroska: "00:00:03.000000000" per track
        try:
            h, m, sec = stream.metadata["DURATION"].split(":")
            seconds, end_time = int(h) * 3600 + int(m) * 60 + float(sec), True
        except ValueError:
            seconds = None
    elif container.duration and len(container.streams) == 1:
        seconds, end_time = container.duration / 1e6, True  # av.time_base
    names = set((container.format.name or "").split(","))
    return (int(stream.frames) if stream.frames else None), seconds, end_time, not names & {"mov", "mp4"}


def _check_complete(path: Path, frames: list, times: list, announced: tuple) -> None:
    """RispError when the file decodes to less than its header announces: a truncated Matroska or AVI file decodes
    without an error, only to fewer frames (an MP4 cut short fails to open).  The decoded frames must reach the
    stream's duration (within two frames or 5 %), and, except in MP4/MOV (whose edit lists announce the frames
    before a stream-copied trim that the decoder drops), number the frames the header counts, less two: an AVI cut
    short keeps its count but ffmpeg rebuilds its duration from what is left."""
    count, seconds, end_time, count_trusted = announced
    n = len(frames)
    # the count less two: an AVI's empty "drop" chunks count as frames (an AVI written with compressed audio has one)
    if count is not None and count_trusted and n < count - 2:
        raise RispError(f"{path}: only {n} of the {count} frames its header announces could be decoded: the file "
                        "is cut short (an interrupted download or copy?)")
    if seconds is not None and len(times) >= 2 and not any(t is None for t in times):
        step = float(np.median(np.diff(times)))
        reached = times[-1] + step if end_time else times[-1] - times[0] + step  # a Matroska video may start late
        if step > 0 and seconds - reached > max(2 * step, 0.05 * seconds):
            raise RispError(f"{path}: the decoded frames end at {reached:.3g} s of the {seconds:.3g} s its header "
                            f"announces ({n} frames): the file is cut short (an interrupted download or copy?)")


#: a step between two frames' timestamps may differ from the median step by this fraction (timestamp rounding,
#: a phone's jitter); a larger one is an irregular step (a frame dropped or held)
RATE_TOLERANCE = 0.5
#: irregular steps allowed as isolated events (noted, not refused): at most this fraction of the steps, or two (one
#: misplaced or repeated timestamp makes two: +d, then −d)
IRREGULAR_FRACTION = 0.01
#: the frames' times may stray this many frame steps from a constant rate (a straight line through the first and
#: the last) before the file counts as having a variable rate
MAX_DRIFT_STEPS = 2.0


def _check_constant_rate(path: Path, times: list) -> str | None:
    """RispError when the frames' presentation times are not those of a constant rate: every task runs its
    simulation at one step per frame, so a variable-frame-rate file would put frames at the wrong times.
    Refused: irregular steps (RATE_TOLERANCE off the median) more often than isolated events (IRREGULAR_FRACTION, or
    two), or times straying more than MAX_DRIFT_STEPS from the constant rate (a rate that changes slowly).
    Isolated ones (an AVI's empty first chunk, one dropped frame or one repeated timestamp) return a note."""
    if len(times) < 3 or any(t is None for t in times):
        return None
    t = np.asarray(times, np.float64)
    steps = np.diff(t)
    median = float(np.median(steps))
    if not median > 0:
        return None
    irregular = np.flatnonzero(np.abs(steps - median) > RATE_TOLERANCE * median)
    mean = (t[-1] - t[0]) / (len(t) - 1)
    drift = float(np.abs(t - t[0] - mean * np.arange(len(t))).max() / mean)
    advice = (f"re-encode it at a constant rate (e.g. ffmpeg -i IN -fps_mode cfr -r {1 / median:.3g} OUT) or export "
              f"its frames as PNGs")
    if len(irregular) > max(2, IRREGULAR_FRACTION * len(steps)) or drift > MAX_DRIFT_STEPS:
        k = int(irregular[0]) if len(irregular) else int(np.argmax(np.abs(steps - median)))
        raise RispError(f"{path}: a variable frame rate ({len(irregular)} of {len(steps)} steps between frames off "
                        f"the usual {median * 1e3:.0f} ms, e.g. frames {k} → {k + 1} {steps[k] * 1e3:.0f} ms apart; "
                        f"times stray up to {drift:.2g} frames from a constant rate): {advice}")
    if len(irregular) or drift > RATE_TOLERANCE:
        k = int(irregular[0]) if len(irregular) else int(np.argmax(np.abs(steps - median)))
        return (f"{path.name}: the frame timestamps stray up to {drift:.2g} frames from a constant rate ({len(irregular)} "
                f"step(s) more than {RATE_TOLERANCE:.0%} off the usual {median * 1e3:.0f} ms, e.g. frames {k} → {k + 1} "
                f"{steps[k] * 1e3:.0f} ms apart: a dropped or held frame?); the tasks take frame k at k / rate")
    return None


#: single still pictures: FFmpeg's image demuxer decodes one at a made-up 25 fps, so their rate is unknown (as a PNG
#: folder's) and --source-fps gives it; animated formats (.gif, .webp, .apng) carry their own timing
STILL_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".exr", ".ppm", ".pgm", ".tga", ".jp2")
OTHER_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".exr", ".gif", ".avif", ".heic", ".heif",
                        ".jp2", ".jxl", ".ppm", ".pgm", ".tga")


def frame_order(path: Path) -> tuple:
    """Sort key of a frame file: numbers in the name compare as numbers, so ``2.png`` comes before ``10.png``
    (plain text order would put frames 10–19 between 1 and 2) and zero-padded names keep their order."""
    parts = re.split(r"(\d+)", path.name)
    return tuple((0, int(x), x) if x.isdigit() else (1, 0, x) for x in parts), path.name


#: files that mark a folder as risp's own output, not a sequence of frames (its PNGs are plots)
_NOT_FRAMES = {"model.pt": "a risp-train run folder", "last.pt": "a risp-train run folder",
               "result.json": "a risp-task result folder", "report.json": "a risp-task diagnose report",
               "manifest.json": "a risp-data shard folder"}


def png_frames(folder: Path) -> list[Path]:
    """A PNG folder's frames in the numeric order of their names (:func:`frame_order`; ``.png`` in any case);
    RispError if it also holds other images, which would otherwise go missing from the sequence without a word,
    or if it is one of risp's output folders (a run's loss plot read as a one-frame video)."""
    for name, what in _NOT_FRAMES.items():
        if (folder / name).is_file():
            raise RispError(f"{folder}: {what} ({name}), not a video: give a video file or a folder of PNG frames")
    files = sorted((f for f in folder.iterdir() if f.is_file() and f.suffix.lower() == ".png"), key=frame_order)
    others = sorted(f.name for f in folder.iterdir() if f.is_file() and f.suffix.lower() in OTHER_IMAGE_SUFFIXES)
    if others:
        raise RispError(f"{folder}: the folder holds images that are not PNG ({others[0]}"
                        f"{f' and {len(others) - 1} more' if len(others) > 1 else ''}): convert them to PNG or move them out")
    return files


def read_rgb8(path: str | os.PathLike) -> np.ndarray:
    """An image file as (H, W, 3) uint8 sRGB.  Alpha is dropped; grey becomes three equal channels; 16-bit
    grey (PIL mode ``I;16``/``I``) is scaled by 255/65535 — PIL's own ``convert("RGB")`` would clip it at 255,
    i.e. read a 16-bit frame as nearly white.  PIL's exceptions propagate (the callers name the file)."""
    from PIL import Image

    with Image.open(path) as im:
        if im.mode.startswith("I;16") or im.mode == "I":
            grey = np.asarray(im, np.float64)
            grey = np.clip(np.round(grey * (255.0 / 65535.0)), 0, 255).astype(np.uint8)
            return np.repeat(grey[..., None], 3, axis=-1)
        if im.mode == "F":
            raise ValueError("32-bit float images are not read (write 8- or 16-bit PNG)")
        return np.asarray(im.convert("RGB"))


def _decode_pngs(folder: Path, each=lambda img: img) -> tuple[list[np.ndarray], tuple[int, int]]:
    """(``each`` of every frame of a PNG folder, in name order; their (width, height): one size for all)."""
    files = png_frames(folder)
    if not files:
        raise RispError(f"{folder}: folder holds no .png frames")
    out, first = [], None
    for f in files:
        try:
            img = read_rgb8(f)
        except Exception as e:  # noqa: BLE001 - PIL raises several types
            raise RispError(f"{f}: cannot read PNG frame ({type(e).__name__}{': ' + str(e) if isinstance(e, ValueError) else ''})") from None
        first = img.shape if first is None else first
        if img.shape != first:
            raise RispError(f"{f}: PNG frame of {img.shape[1]}×{img.shape[0]} pixels, but {files[0].name} "
                            f"has {first[1]}×{first[0]}: the frames of a video share one size")
        out.append(each(img))
    return out, (first[1], first[0])


def resize(frames: np.ndarray, resolution: int) -> np.ndarray:
    """(T, H, W, 3) linear RGB -> (T, r, r, 3): centre crop to a square, then area/bilinear resampling."""
    import torch
    import torch.nn.functional as F

    T, H, W, _ = frames.shape
    side = min(H, W)
    top, left = (H - side) // 2, (W - side) // 2
    x = torch.from_numpy(np.ascontiguousarray(frames[:, top:top + side, left:left + side])).permute(0, 3, 1, 2)
    if side == resolution:
        out = x
    elif side > resolution:
        out = F.interpolate(x, size=(resolution, resolution), mode="area")
    else:
        out = F.interpolate(x, size=(resolution, resolution), mode="bilinear", align_corners=False)
    return out.permute(0, 2, 3, 1).contiguous().numpy().astype(np.float32)


#: how far (as a fraction) the source rate / --fps ratio may be from a whole number: 29.97 fps to 10 is 2.997
RATE_RATIO_TOLERANCE = 0.01


def sample_indices(n: int, source_fps: float, fps: float | None, every: int) -> list[int]:
    """Frame indices after resampling to ``fps`` (nearest frame) and keeping every ``every``-th.

    Resampled frame k is the source frame nearest to t_k = k / fps, for every t_k up to the last frame's time
    (n − 1) / source_fps.  Resampling only drops frames: an ``fps`` above the source's own rate would have to invent
    the frames between, so it is an error; so is a rate that does not divide the source's (30 → 20 fps would keep
    frames 0, 2, 3, 4, 6, …, unevenly spaced, while the tasks take them 1/fps apart)."""
    if every < 1:
        raise RispError(f"--every must be a positive integer, got {every}")
    idx = list(range(n))
    if fps is not None:
        if not (math.isfinite(fps) and fps > 0):
            raise RispError(f"--fps must be a positive finite number, got {fps}")
        if not source_fps > 0:
            raise RispError("--fps needs the video's own frame rate, which this source does not carry (a PNG folder: give --source-fps)")
        if fps > source_fps * (1 + 1e-9):
            raise RispError(f"--fps {fps:g} is above the video's own {source_fps:g} frames per second: resampling "
                            f"only drops frames, it cannot make new ones (give --fps at most {source_fps:g})")
        ratio = source_fps / fps
        if abs(ratio - round(ratio)) > RATE_RATIO_TOLERANCE * ratio:
            rates = ", ".join(f"{source_fps / k:.4g}" for k in range(1, 5))
            raise RispError(f"--fps {fps:g} does not divide the video's {source_fps:g} frames per second (ratio "
                            f"{ratio:.3g}): the kept frames would be unevenly spaced in time; give {source_fps:g}/k "
                            f"({rates}, …)")
        count = int(np.floor((n - 1) * fps / source_fps + 1e-9)) + 1  # every t_k <= the last frame's time
        idx = sorted({min(n - 1, int(round(k * ratio))) for k in range(count)})
    return idx[::every]


def read_video(path: str | os.PathLike, resolution: int | None = None, every: int = 1, fps: float | None = None,
               source_fps: float | None = None) -> Video:
    """Decode ``path`` (video file or PNG folder) to linear RGB frames, resampled in time and size.

    ``source_fps`` gives the frame rate of a PNG folder; on a file it replaces the rate the file carries (slow
    motion stored at 30 fps), which ``notes`` then says."""
    p = Path(path)
    if not p.exists():
        raise RispError(f"{p}: no such file or folder")
    if source_fps is not None and not (math.isfinite(source_fps) and source_fps > 0):
        raise RispError(f"--source-fps must be a positive finite number, got {source_fps:g}")
    def each(img: np.ndarray) -> np.ndarray:
        """A decoded frame as kept until the sampling below: at the network's resolution when one is given (a
        full-size copy of every frame of a long 1080p clip would not fit in memory), else as decoded."""
        return img if resolution is None else resize(SRGB8_TO_LINEAR[img][None], int(resolution))[0]

    comment, notes = "", []
    if p.is_dir():
        (raw, size), rate = _decode_pngs(p, each), float(source_fps or 0.0)
        comment = _png_comment(p)
    else:
        if p.stat().st_size == 0:
            raise RispError(f"{p}: empty file (0 bytes)")
        raw, rate, comment, size, notes = _decode_file(p, each)
        if p.suffix.lower() in STILL_IMAGE_SUFFIXES:  # the demuxer's 25 fps is no property of the picture
            rate = 0.0
        if source_fps is not None and rate and abs(source_fps - rate) > 1e-6 * rate:  # e.g. slow motion stored at 30
            notes.append(f"--source-fps {source_fps:g} replaces the {rate:g} fps written in {p.name}: its frames are "
                         f"taken {1 / source_fps:.4g} s apart")
        rate = float(source_fps or rate)
    if not raw:
        raise RispError(f"{p}: the video has no frames")
    idx = sample_indices(len(raw), rate, fps, every)
    if not idx:
        raise RispError(f"{p}: no frames left after --fps {fps} / --every {every}")
    frames = np.stack([raw[i] for i in idx])
    if resolution is None:
        frames = SRGB8_TO_LINEAR[frames]
    out_fps = (fps if fps is not None else rate) / every if (fps or rate) else 0.0
    return Video(frames=frames, fps=float(out_fps), source=str(p), source_frames=len(raw), indices=tuple(idx),
                 source_fps=float(rate), comment=comment, notes=tuple(notes), source_size=size)


#: the comment tag of make-video's files: "risp make-video env=<env> seed=<seed>" (made_by / made_for)
MADE_BY = "risp make-video"


def made_by(env: str, seed: int) -> str:
    return f"{MADE_BY} env={env} seed={seed}"


def comment_tag(path: str | os.PathLike) -> str:
    """The container's comment tag, read from the header (nothing decoded); for a PNG folder its first frame's
    ``Comment`` chunk; "" for a file or folder without one, or one that cannot be opened (reading it in full
    reports that)."""
    if os.path.isdir(path):
        return _png_comment(Path(path))
    if not os.path.isfile(path):
        return ""
    try:
        with _av().open(str(path)) as container:
            return _comment(container)
    except Exception:  # noqa: BLE001 - not a video: the full read says so in one line
        return ""


def _png_comment(folder: Path) -> str:
    """A PNG folder's comment: its first frame's ``Comment`` text chunk (make-video writes one into every frame)."""
    from PIL import Image

    try:
        frames = png_frames(folder)
        if not frames:
            return ""
        with Image.open(frames[0]) as im:
            return str((getattr(im, "text", {}) or {}).get("Comment", ""))
    except Exception:  # noqa: BLE001 - not a folder of frames, an unreadable frame: the full read says so in one line
        return ""


def _comment(container) -> str:
    """An open container's comment tag ("" without one); Matroska writes it as COMMENT."""
    return str({k.lower(): v for k, v in container.metadata.items()}.get("comment", ""))


def made_for(comment: str) -> str | None:
    """The environment a make-video file names in its comment tag, None for any other file."""
    if not comment.startswith(MADE_BY + " "):
        return None
    fields = dict(part.split("=", 1) for part in comment[len(MADE_BY) + 1:].split() if "=" in part)
    return fields.get("env")


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: float, crf: int = 12,
                overwrite: bool = False, comment: str | None = None, exclusive: bool = False) -> str:
    """Write linear-RGB frames (T, H, W, 3) as a video (by suffix: H.264 in .mp4/.mkv/.mov, MPEG-4 Part 2
    in .avi) or, for any other path, a folder of PNGs ``frame_00000.png`` …; atomically.  Another media suffix
    (``.gif``: :data:`OTHER_MEDIA_SUFFIXES`) is an error, not a folder of that name.  A video file is replaced; a PNG folder only with
    ``overwrite`` and only when it holds nothing but PNG frames.  ``comment``: the file's comment tag (files only).
    ``exclusive``: replace nothing — FileExistsError when a video (or a non-empty folder) is at ``path`` when it
    is published, also one another process wrote meanwhile.  Returns the :func:`sha256_file` of what was written,
    taken before it is published (the file at ``path`` may be another writer's a moment later)."""
    frames = np.asarray(frames)
    p = Path(path)
    check_video_path(p, overwrite)
    if frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) == 0:
        raise RispError(f"frames must have shape (T>0, H, W, 3), got {frames.shape}")
    if not np.isfinite(frames).all():
        raise RispError("frames contain NaN or inf")
    data = to_uint8(frames)
    if p.suffix.lower() not in VIDEO_SUFFIXES:
        return _write_pngs(p, data, comment, exclusive)
    av = _av()
    H, W = data.shape[1:3]
    import io
    from fractions import Fraction

    encoded = io.BytesIO()  # encoded in memory (far smaller than the frames themselves), hashed, then published
    with av.open(encoded, mode="w", format={".mp4": "mp4", ".mkv": "matroska", ".mov": "mov", ".avi": "avi"}[p.suffix.lower()]) as out:
        if comment:
            out.metadata["comment"] = comment
        stream = out.add_stream(CODECS[p.suffix.lower()], rate=Fraction(fps).limit_denominator(1000))
        stream.width, stream.height = W, H
        stream.pix_fmt = "yuv444p" if CODECS[p.suffix.lower()] == "libx264" else "yuv420p"
        if CODECS[p.suffix.lower()] == "libx264":
            stream.options = {"crf": str(crf), "preset": "medium"}
        else:
            stream.bit_rate = 8_000_000
        for img in data:
            for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    blob = encoded.getvalue()
    with atomic_write(p, "wb", suffix=p.suffix, exclusive=exclusive) as f:
        f.write(blob)
    return hashlib.sha256(blob).hexdigest()


#: suffixes of video and image files write_video cannot write: such a path is an error, not a PNG folder of that
#: name (any other path without a video suffix, e.g. "clip-1.5" or "run.v2", is a folder of PNG frames)
OTHER_MEDIA_SUFFIXES = (".gif", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".ogv", ".3gp", ".ts", ".mts",
                        ".apng", ".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".exr")


def check_video_path(path: str | os.PathLike, overwrite: bool = False) -> None:
    """A path ``write_video`` can write, checked before any rendering: a video suffix, or a folder of PNG frames
    (new, empty, or — with ``overwrite`` — holding nothing but PNG files); a file of another media type is an
    error."""
    p = Path(path)
    if p.suffix.lower() in OTHER_MEDIA_SUFFIXES:
        raise RispError(f"{p}: cannot write {p.suffix} videos; give a path ending in "
                        f"{', '.join(VIDEO_SUFFIXES)}, or a folder name for PNG frames")
    if p.suffix.lower() in VIDEO_SUFFIXES and p.is_dir():  # found only when the rendered video is published
        raise RispError(f"{p}: an existing folder, not a video file; give a new file name (or a folder name "
                        f"without {p.suffix} for PNG frames)")
    if p.suffix.lower() in VIDEO_SUFFIXES or not p.exists():
        return
    if not p.is_dir():
        raise RispError(f"{p}: exists and is not a folder of PNG frames")
    held = list(p.iterdir())
    if held and not overwrite:
        raise RispError(f"{p}: folder exists and is not empty (--overwrite replaces a folder of PNG frames)")
    if any(not (f.is_file() and f.suffix.lower() == ".png") for f in held):  # never delete what is not ours
        raise RispError(f"{p}: holds files other than PNG frames; give another --out")


def _write_pngs(folder: Path, data: np.ndarray, comment: str | None = None, exclusive: bool = False) -> str:
    """The frames as ``frame_NNNNN.png`` in a new folder renamed into place (``exclusive``: only onto nothing or an
    empty folder); ``comment`` (make-video's "risp make-video env=… seed=…") goes into each frame's ``Comment`` text
    chunk, as a video file's comment tag.  Returns the new folder's :func:`sha256_file`, taken before it is
    published."""
    import shutil

    from PIL import Image

    from risp_data.atomic import replace_folder, temp_folder

    folder.parent.mkdir(parents=True, exist_ok=True)  # (write_video checked the path: check_video_path)
    from PIL.PngImagePlugin import PngInfo

    info = PngInfo()
    if comment:
        info.add_text("Comment", comment)
    tmp = Path(temp_folder(folder.parent))
    try:
        for i, img in enumerate(data):
            Image.fromarray(img).save(tmp / f"frame_{i:05d}.png", pnginfo=info)
        digest = sha256_file(tmp)
        if exclusive:
            try:
                os.rename(tmp, folder)  # onto nothing or an empty folder; a folder of frames stays (ENOTEMPTY)
            except OSError as e:
                if e.errno in (errno.ENOTEMPTY, errno.EEXIST):
                    raise FileExistsError(errno.EEXIST, "exists", str(folder)) from None
                raise
        else:
            replace_folder(tmp, folder)  # an old folder of frames (--overwrite) goes only once the new one is in place
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return digest


__all__ = ["Video", "check_video_path", "read_video", "read_rgb8", "png_frames", "write_video", "resize", "sample_indices", "srgb_to_linear", "linear_to_srgb",
           "sha256_file", "to_uint8"]
