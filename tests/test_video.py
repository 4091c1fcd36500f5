"""Video I/O (risp_tasks.video): write/read round trips, resizing, temporal sampling, bad files."""

import numpy as np
import pytest

from risp_data.errors import RispError

pytest.importorskip("av")
from risp_tasks.video import linear_to_srgb, read_video, sample_indices, srgb_to_linear, write_video  # noqa: E402


def _frames(T=12, H=48, W=64):
    y, x = np.mgrid[0:H, 0:W] / max(H, W)
    return np.stack([np.clip((0.1 + 0.7 * x * y * (t + 1) / T)[..., None] * np.array([1.0, 0.7, 0.4]), 0, 1)
                     for t in range(T)]).astype(np.float32)


@pytest.mark.parametrize("name, tol, size", [("v.mp4", 0.03, (48, 64)), ("v.avi", 0.06, (48, 64)),
                                            ("pngs", 0.005, (48, 64)), ("odd.mp4", 0.03, (9, 9)),
                                            ("odd.mkv", 0.03, (33, 17))])
def test_round_trip_within_codec_tolerance(tmp_path, name, tol, size):
    """Odd sizes included: H.264 in 4:4:4 (the writer's pixel format) takes them, unlike 4:2:0."""
    frames = _frames(H=size[0], W=size[1])
    write_video(tmp_path / name, frames, fps=10)
    video = read_video(tmp_path / name, source_fps=10)
    assert video.frames.shape == frames.shape and video.fps == 10
    err = np.abs(linear_to_srgb(video.frames) - linear_to_srgb(frames))  # compare in the stored (sRGB) space
    assert err.max() < tol and err.mean() < tol / 4, (err.max(), err.mean())
    # the frames are distinguishable: each decoded frame is closest to its own original
    d = np.abs(video.frames[:, None] - frames[None]).mean((2, 3, 4))
    assert (d.argmin(1) == np.arange(len(frames))).all()


def test_resize_every_and_fps(tmp_path):
    write_video(tmp_path / "v.mp4", _frames(T=20), fps=20)
    v = read_video(tmp_path / "v.mp4", resolution=16, every=3)
    assert v.frames.shape == (7, 16, 16, 3) and v.indices == tuple(range(0, 20, 3)) and v.fps == pytest.approx(20 / 3)
    v = read_video(tmp_path / "v.mp4", fps=5)
    assert v.indices == (0, 4, 8, 12, 16) and v.fps == 5
    # area resize of a constant image keeps its value
    write_video(tmp_path / "c.mp4", np.full((2, 32, 48, 3), 0.25, np.float32), fps=10)
    assert np.allclose(read_video(tmp_path / "c.mp4", resolution=8).frames, 0.25, atol=0.01)


def test_srgb_curves_are_inverse():
    x = np.linspace(0, 1, 101, dtype=np.float32)
    assert np.allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-5)
    assert sample_indices(10, 10.0, None, 4) == [0, 4, 8]


def test_resampling_keeps_the_last_frame_and_even_spacing():
    """Resampled frame k is the source frame at k / fps, up to the last frame's time: 21 frames at 10 fps end at
    2.0 s, which 5 fps keeps (frame 20); a rate that does not divide the source's is refused (uneven spacing);
    29.97 fps to 10 is a whole ratio within tolerance."""
    from risp_data.errors import RispError

    assert sample_indices(21, 10.0, 5.0, 1) == list(range(0, 21, 2))
    assert sample_indices(20, 10.0, 5.0, 1) == list(range(0, 20, 2))
    assert sample_indices(31, 30.0, 10.0, 1) == list(range(0, 31, 3))
    assert sample_indices(7, 10.0, 10.0, 1) == list(range(7))
    assert sample_indices(31, 30.0, 10.0, 2) == [0, 6, 12, 18, 24, 30]
    with pytest.raises(RispError, match=r"--fps 20 does not divide the video's 30 frames per second \(ratio 1.5\)"):
        sample_indices(30, 30.0, 20.0, 1)
    ntsc = sample_indices(300, 29.97, 10.0, 1)
    assert len(ntsc) == 100 and np.all(np.abs(np.diff(ntsc) - 3) <= 1)


def _make(path, data):
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("make, message", [
    (lambda p: p / "missing.mp4", "no such file"),
    (lambda p: _make(p / "empty.mp4", b""), "empty file"),
    (lambda p: _make(p / "text.mp4", b"not a video at all\n" * 20), "cannot decode"),
    (lambda p: (p / "d").mkdir() or p / "d", "no .png frames"),
])
def test_bad_video_files(tmp_path, make, message):
    path = make(tmp_path)
    with pytest.raises(RispError, match=message) as e:
        read_video(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)
    assert "Errno" not in str(e.value)  # the decoder's words, not its error number


@pytest.mark.parametrize("name, message", [("notes.txt", "not a video .*format tty, codec ansi"),
                                           ("notes.md", "cannot decode as a video"),
                                           ("notes.mp4", "cannot decode as a video")])
def test_a_text_file_is_not_footage(tmp_path, name, message):
    """FFmpeg's tty demuxer reads a few kB of text as ANSI art, a "video" of drawn characters (a README passed
    as the video used to run a whole task, exit 0): refused by its codec. Named .mp4, the mp4 demuxer refuses it."""
    text = "".join(f"line {i}: a paragraph of notes, not footage of anything at all.\n" for i in range(80))
    path = _make(tmp_path / name, text.encode())
    with pytest.raises(RispError, match=message) as e:
        read_video(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_truncated_video_is_refused_or_short(tmp_path):
    write_video(tmp_path / "v.mp4", _frames(T=30), fps=10)
    data = (tmp_path / "v.mp4").read_bytes()
    (tmp_path / "cut.mp4").write_bytes(data[: len(data) // 3])
    with pytest.raises(RispError, match="cut.mp4"):
        read_video(tmp_path / "cut.mp4")


def test_fps_above_the_source_rate_is_refused(tmp_path):
    """Resampling picks frames; it cannot make new ones: a higher --fps used to keep every frame and label the
    clip as twice as fast (a 1.3 s clip read as 0.65 s, exit 0)."""
    write_video(tmp_path / "v.mp4", _frames(T=12), fps=10)
    with pytest.raises(RispError, match=r"--fps 20 is above the video's own 10 frames per second"):
        read_video(tmp_path / "v.mp4", fps=20)
    assert read_video(tmp_path / "v.mp4", fps=10).indices == tuple(range(12))  # equal rates: every frame
    for bad in (float("inf"), float("nan"), -5.0):
        with pytest.raises(RispError, match="--fps must be a positive finite number"):
            read_video(tmp_path / "v.mp4", fps=bad)
    for bad in (float("inf"), 0.0, -10.0):
        with pytest.raises(RispError, match="--source-fps must be a positive finite number"):
            read_video(tmp_path / "v.mp4", source_fps=bad)


def test_png_frames_of_every_depth_and_case(tmp_path):
    """16-bit grey PNGs are read at their brightness (PIL's convert("RGB") clips them to white), grey and
    RGBA frames become RGB, upper-case .PNG names count, and other images or sizes in the folder are named."""
    from PIL import Image

    folder = tmp_path / "f"
    folder.mkdir()
    ramp = np.linspace(0, 65535, 16 * 16).reshape(16, 16).astype(np.uint16)
    Image.fromarray(ramp).save(folder / "frame_00000.png")
    assert Image.open(folder / "frame_00000.png").mode.startswith("I")
    Image.fromarray((ramp // 257).astype(np.uint8)).save(folder / "frame_00001.PNG")
    Image.fromarray(np.dstack([(ramp // 257).astype(np.uint8)] * 3 + [np.full((16, 16), 128, np.uint8)])).save(
        folder / "frame_00002.png")
    v = read_video(folder, source_fps=10)
    assert v.frames.shape == (3, 16, 16, 3)
    assert np.allclose(v.frames[0], v.frames[1], atol=1e-6) and np.allclose(v.frames[0], v.frames[2], atol=1e-6)
    assert abs(float(linear_to_srgb(v.frames[0]).mean()) - 0.5) < 0.01  # a ramp, not a white frame
    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(folder / "frame_00003.jpg")
    with pytest.raises(RispError, match=r"not PNG \(frame_00003.jpg\)"):
        read_video(folder, source_fps=10)
    (folder / "frame_00003.jpg").unlink()
    Image.fromarray(np.zeros((8, 16, 3), np.uint8)).save(folder / "frame_00004.png")
    with pytest.raises(RispError, match=r"frame_00004.png: PNG frame of 16×8 pixels, but frame_00000.png has 16×16"):
        read_video(folder, source_fps=10)


@pytest.mark.parametrize("name", ["clip.mp4", "frames"])
def test_frames_are_reduced_to_the_resolution_as_they_are_decoded(tmp_path, name):
    """A task's video is held at the network's resolution, not at the camera's: 40 frames of 512×512 are 31 MB
    as decoded (the whole clip used to be kept so until the sampling); read at 16×16 the peak stays below that —
    and the frames equal those resized after decoding at full size."""
    import tracemalloc

    from risp_tasks.video import resize

    rng = np.random.default_rng(0)
    path = str(tmp_path / name)
    write_video(path, rng.random((40, 512, 512, 3), dtype=np.float32) * 0.1, fps=10)
    tracing = tracemalloc.is_tracing()  # a caller's own tracing (-X tracemalloc) is left on
    tracemalloc.start()
    tracemalloc.reset_peak()
    try:
        small = read_video(path, resolution=16, every=3)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        if not tracing:
            tracemalloc.stop()
    assert small.frames.shape == (14, 16, 16, 3) and small.source_frames == 40
    # below the decoded clip's own 31 MB (measured: 14 MB, one frame's float temporaries; 190-220 MB before)
    assert peak < 40 * 512 * 512 * 3, peak
    assert np.array_equal(small.frames, resize(read_video(path, every=3).frames, 16))


def test_a_frame_conversion_error_is_not_called_a_decoding_error(tmp_path, monkeypatch):
    """The frames are converted while the decoder runs; an error of the conversion (here out of memory) is raised as
    what it is, not reported as "cannot decode as a video"."""
    import risp_tasks.video as video

    path = str(tmp_path / "clip.mp4")
    write_video(path, np.full((3, 16, 16, 3), 0.5, np.float32), fps=10)

    def no_memory(*_args, **_kw):
        raise MemoryError("resize")

    monkeypatch.setattr(video, "resize", no_memory)
    with pytest.raises(MemoryError, match="resize"):
        read_video(path, resolution=8)


def test_png_frames_with_unpadded_numbers_are_read_in_numeric_order(tmp_path):
    """1.png … 12.png: text order (1, 10, 11, 12, 2, …) shuffled the frames without a word."""
    from PIL import Image

    folder = tmp_path / "unpadded"
    folder.mkdir()
    for i in range(1, 13):  # frame i is uniformly i·20 grey
        Image.fromarray(np.full((8, 8, 3), 20 * i, np.uint8)).save(folder / f"{i}.png")
    v = read_video(folder, source_fps=10)
    grey = np.round(linear_to_srgb(v.frames[:, 0, 0, 0]) * 255).astype(int)
    assert grey.tolist() == [20 * i for i in range(1, 13)]


@pytest.mark.parametrize("suffix", [".mkv", ".avi"])
def test_a_cut_matroska_or_avi_file_is_refused_not_read_short(tmp_path, suffix):
    """A truncated .mkv/.avi decodes without an error, only to fewer frames: it was read as a shorter video (exit
    0, or an actions file blamed for the count).  The header's frame count or duration names the cut."""
    write_video(tmp_path / f"v{suffix}", _frames(T=30), fps=10)
    assert read_video(tmp_path / f"v{suffix}").frames.shape[0] == 30  # whole: read as it is
    data = (tmp_path / f"v{suffix}").read_bytes()
    (tmp_path / f"cut{suffix}").write_bytes(data[: len(data) * 9 // 10])  # (cut shorter, this AVI does not open)
    with pytest.raises(RispError, match=rf"cut{suffix}: .*the file is cut short"):
        read_video(tmp_path / f"cut{suffix}")


def _write_with_times(path, frames, times_ms):
    """A video whose frames have the given presentation times (ms): a variable frame rate."""
    import av
    from fractions import Fraction

    from risp_tasks.video import to_uint8

    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv444p"
        stream.time_base = Fraction(1, 1000)
        for img, t in zip(to_uint8(frames), times_ms):
            f = av.VideoFrame.from_ndarray(img, format="rgb24")
            f.pts, f.time_base = t, Fraction(1, 1000)
            for packet in stream.encode(f):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)


def test_a_variable_frame_rate_video_is_refused(tmp_path):
    """Every fifth gap 300 ms instead of 100: the tasks put frame k at k / rate, so such a file was read with
    wrong times (exit 0).  Evenly spaced times pass."""
    frames = _frames(T=20, H=16, W=16)
    even = [100 * k for k in range(20)]
    _write_with_times(tmp_path / "even.mkv", frames, even)
    assert read_video(tmp_path / "even.mkv").frames.shape[0] == 20
    uneven = np.cumsum([0] + [300 if k % 5 == 4 else 100 for k in range(19)]).tolist()
    _write_with_times(tmp_path / "vfr.mkv", frames, uneven)
    with pytest.raises(RispError, match=r"vfr.mkv: a variable frame rate \(\d+ of 19 steps between frames off the "
                                        r"usual 100 ms, e.g. frames \d+ → \d+ 300 ms apart"):
        read_video(tmp_path / "vfr.mkv")
    # one dropped frame, or one late timestamp (two irregular steps: +d, then −d), is said, not refused
    dropped = [100 * k for k in range(10)] + [100 * k for k in range(11, 21)]
    late = [100 * k + (50 if k == 7 else 0) for k in range(20)]
    for name, times in (("drop.mkv", dropped), ("late.mkv", late)):
        _write_with_times(tmp_path / name, frames, times)
        v = read_video(tmp_path / name)
        assert v.frames.shape[0] == 20 and len(v.notes) == 1 and "a dropped or held frame?" in v.notes[0], name
    # a Matroska video that starts late (its DURATION tag is an end time from 0) is whole
    _write_with_times(tmp_path / "starts_late.mkv", frames, [500 + 100 * k for k in range(20)])
    assert read_video(tmp_path / "starts_late.mkv").notes == ()


def _synthetic_clip(path, n, fps=30, gop=None, audio_seconds=None):
    """An H.264 clip of n frames (keyframe every ``gop``), with a silent AAC track of ``audio_seconds``."""
    import av

    with av.open(str(path), "w") as out:
        vs = out.add_stream("libx264", rate=fps)
        vs.width, vs.height, vs.pix_fmt = 32, 24, "yuv420p"
        if gop:
            vs.options = {"g": str(gop), "bf": "0"}
        audio = out.add_stream("aac", rate=48000) if audio_seconds else None
        for i in range(n):
            f = av.VideoFrame.from_ndarray(np.full((24, 32, 3), (i * 2) % 255, np.uint8), format="rgb24")
            for p in vs.encode(f):
                out.mux(p)
        for p in vs.encode():
            out.mux(p)
        k = 0
        while audio is not None and k < audio_seconds * 48000:
            af = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp", layout="mono")
            af.sample_rate, af.pts = 48000, k
            for p in audio.encode(af):
                out.mux(p)
            k += 1024
        for p in (audio.encode() if audio is not None else []):
            out.mux(p)


@pytest.mark.parametrize("suffix", [".mp4", ".mov", ".mkv"])
def test_a_stream_copy_trim_and_a_longer_audio_track_are_whole_files(tmp_path, suffix):
    """Not every short decode is a cut: a stream-copied trim (ffmpeg -ss 1 -c copy) keeps the packets back to the
    last keyframe, which the decoder drops (an MP4's edit list; the header's frame count still holds them), and a
    sound track may run longer than the picture (a Matroska file's container duration is the longest stream's)."""
    import av

    src = tmp_path / "src.mp4"
    _synthetic_clip(src, 120, gop=60)
    trimmed = tmp_path / f"trim{suffix}"
    with av.open(str(src)) as inp, av.open(str(trimmed), "w") as out:
        ist = inp.streams.video[0]
        ost = out.add_stream_from_template(ist)
        shift = int(round(1.0 / ist.time_base))  # 1 s, mid-GOP: frames 30–59 need the keyframe at 0
        for pk in inp.demux(ist):
            if pk.dts is None:
                continue
            pk.pts, pk.dts, pk.stream = pk.pts - shift, pk.dts - shift, ost
            out.mux(pk)
    assert read_video(trimmed).frames.shape[0] >= 90
    _synthetic_clip(tmp_path / f"sound{suffix}", 30, audio_seconds=3.0)  # 1 s of picture, 3 s of sound
    v = read_video(tmp_path / f"sound{suffix}")
    assert v.frames.shape[0] == 30 and v.notes == ()


def test_source_fps_on_a_file_replaces_its_rate_and_says_so(tmp_path):
    write_video(tmp_path / "v.mp4", _frames(T=6), fps=10)
    assert read_video(tmp_path / "v.mp4").notes == ()
    v = read_video(tmp_path / "v.mp4", source_fps=20)
    assert v.fps == 20 and len(v.notes) == 1 and "--source-fps 20 replaces the 10 fps written in v.mp4" in v.notes[0]


@pytest.mark.parametrize("other", ["frame_00002.gif", "frame_00002.tga"])
def test_other_image_kinds_in_a_png_folder_are_named(tmp_path, other):
    from PIL import Image

    folder = tmp_path / "f"
    folder.mkdir()
    for i in range(2):
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(folder / f"frame_{i:05d}.png")
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(folder / other)
    with pytest.raises(RispError, match=rf"not PNG \({other}\)"):
        read_video(folder, source_fps=10)


def _with_display_matrix(src, dst, matrix):
    """Copy an MP4 with its video track's display matrix (the tkhd box, version 0) replaced by any 3×3 matrix — how
    a phone marks a clip filmed upright; flips and degenerate matrices included."""
    import struct

    data = bytearray(src.read_bytes())
    i = data.index(b"tkhd")
    assert data[i + 4] == 0  # version 0: the matrix follows 40 bytes of times, ids, duration, layer, volume
    off = i + 4 + 4 + 4 + 4 + 4 + 4 + 4 + 8 + 2 + 2 + 2 + 2
    data[off:off + 36] = struct.pack(">9i", *matrix)
    dst.write_bytes(bytes(data))


def test_a_phone_clip_filmed_upright_is_read_upright(tmp_path):
    """A display matrix of −90° (ffmpeg: "rotation of -90.00 degrees", autorotated clockwise): the frames are turned
    as a player shows them — the landscape frame's bright left strip ends up at the top of a portrait frame — and
    the turn is said.  Ignored, the network saw the scene sideways."""
    img = np.zeros((4, 16, 32, 3), np.float32)
    img[:, :, :8] = 1.0  # a bright strip on the left
    write_video(tmp_path / "land.mp4", img, fps=10)
    _with_display_matrix(tmp_path / "land.mp4", tmp_path / "upright.mp4", (0, 65536, 0, -65536, 0, 0, 0, 0, 1 << 30))
    v = read_video(tmp_path / "upright.mp4")
    assert v.frames.shape == (4, 32, 16, 3) and v.source_size == (16, 32)
    assert v.frames[:, :8].mean() > 0.9 and v.frames[:, 24:].mean() < 0.05  # the strip on top
    assert len(v.notes) == 1 and "frames turned 90° clockwise, as its display matrix says" in v.notes[0]
    assert read_video(tmp_path / "land.mp4").frames.shape == (4, 16, 32, 3)


def test_a_mirroring_display_matrix_is_refused_and_a_degenerate_one_ignored(tmp_path):
    """A flip (determinant < 0) is not applied by risp: one line, not frames turned the wrong way; an all-zero
    matrix is no transformation (ffmpeg plays such a file as stored)."""
    write_video(tmp_path / "land.mp4", _frames(T=3, H=16, W=32), fps=10)
    _with_display_matrix(tmp_path / "land.mp4", tmp_path / "mirror.mp4", (-65536, 0, 0, 0, 65536, 0, 0, 0, 1 << 30))
    with pytest.raises(RispError, match="mirror.mp4: its display matrix mirrors the frames"):
        read_video(tmp_path / "mirror.mp4")
    _with_display_matrix(tmp_path / "land.mp4", tmp_path / "zero.mp4", (0,) * 9)
    v = read_video(tmp_path / "zero.mp4")
    assert v.frames.shape == (3, 16, 32, 3) and v.notes == ()


def test_an_avi_cut_anywhere_is_refused_or_whole(tmp_path):
    """An AVI cut short keeps its header's frame count while ffmpeg rebuilds its duration from the chunks left:
    wherever it is cut, reading it either refuses it or gives all but at most two frames — never a shorter video."""
    write_video(tmp_path / "v.avi", _frames(T=90, H=24, W=32), fps=30)
    data = (tmp_path / "v.avi").read_bytes()
    shorter, whole = [], []
    for percent in range(50, 100, 5):
        cut = tmp_path / f"cut{percent}.avi"
        cut.write_bytes(data[: len(data) * percent // 100])
        try:
            n = read_video(cut).frames.shape[0]
        except RispError:
            continue
        if n < 88:  # the last two frames are within the count's slack (an AVI's empty chunks count as frames)
            shorter.append((percent, n))
        else:
            whole.append(percent)
    assert shorter == []
    assert whole  # a reader that refused every AVI would pass the line above: the near-whole cuts are read
