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
