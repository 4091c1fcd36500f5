"""risp-task estimate / sysid / imitate / control end to end on a tiny configuration (a real tiny trained
network, a real target-domain reference video, real simulators and renderer): each runs, lowers its loss and
writes a complete result folder."""

import json
import os

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from tasks_helpers import RES, shared_model, shared_video, vehicle_obj

pytest.importorskip("av")
pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def quad(tmp_path_factory):
    return shared_model(tmp_path_factory, "quadrotor"), shared_video(tmp_path_factory, "quadrotor")


def _run(task, video, out, **kw):
    from risp_tasks.tasks.config import TaskConfig
    from risp_tasks.tasks.run import run_task

    return run_task(TaskConfig(task=task, video=video, out=str(out), progress=False, **kw), echo=lambda s: None)


def _stem(video):
    return os.path.splitext(video)[0]


def test_make_video_writes_video_truth_and_actions(quad):
    from risp_tasks.video import read_video

    _, video = quad
    truth = json.load(open(_stem(video) + ".truth.json"))
    v = read_video(video)
    assert v.frames.shape == (6, RES, RES, 3) and v.fps == 10
    assert len(truth["env_states"]) == 6 and truth["look"]["domain"] == "target" and truth["seed"] == 3
    assert 2.8 <= truth["params"]["mass"] < 3.2
    assert np.asarray(truth["actions"]).shape == (6, 4)
    # the states move: the video is not a still
    assert np.ptp(np.asarray(truth["env_states"])[:, :3], 0).max() > 0.01


@pytest.mark.parametrize("init", ["default", "track"])
def test_imitate_prints_the_parameters_params_gave(quad, tmp_path, init):
    """imitate --params: the values it simulated with are printed (they were only in result.json), the fitted
    ones where they ended instead; with --init track too (its result.json recorded neither)."""
    from click.testing import CliRunner

    from risp_tasks.cli import cli

    model, video = quad
    res = CliRunner().invoke(cli, ["imitate", video, "--model", model, "--params", '{"mass": 3.05}', "--iterations", "1",
                                   "--init", init, "--out", str(tmp_path / "o"), "--quiet", "--no-plots"])
    assert res.exit_code == 0, res.output
    assert "  mass = 3.05 (from --params)" in res.output.splitlines()
    saved = json.load(open(tmp_path / "o" / "result.json"))
    assert saved["info"]["given_parameters"] == {"mass": 3.05}
    assert saved["info"]["parameters"]["mass"] == 3.05


def test_a_truth_file_beside_the_video_is_pointed_at_not_read(quad, tmp_path):
    """make-video's <stem>.truth.json beside the video: without --truth the result says how to compare with it
    (no solver reads it, so no errors are reported); with --truth the errors are there and the hint is not."""
    model, video = quad
    r = _run("estimate", video, tmp_path / "a", model=model, plots=False)
    beside = _stem(video) + ".truth.json"
    assert r["errors"] == {} and any(f"add --truth {beside} to see the errors" in w for w in r["warnings"])
    r = _run("estimate", video, tmp_path / "b", model=model, plots=False, truth=beside)
    assert "state_rmse_network" in r["errors"] and not any("lies beside the video" in w for w in r["warnings"])


def test_estimate_writes_measured_csv_that_diagnose_reads(quad, tmp_path):
    from risp_tasks.measured import load_measured

    model, video = quad
    r = _run("estimate", video, tmp_path / "est", model=model, actions=_stem(video) + ".actions.csv",
             truth=_stem(video) + ".truth.json")
    traj = load_measured([str(tmp_path / "est" / "trajectory.csv")], "quadrotor")[0]
    assert traj.n == 6 and traj.thrust is not None
    assert np.allclose(traj.thrust, np.loadtxt(_stem(video) + ".actions.csv", delimiter=",", skiprows=1)[:, 1:])
    # the pose columns are the estimates: position as read, the quaternion (scalar first) turned back into
    # R = Rz(yaw) Ry(pitch) Rx(roll) gives the estimated angles; signs continuous from row to row; t = frame / fps
    est = np.asarray(r["estimates"]["env_states"], np.float64)
    np.testing.assert_allclose(traj.pos, est[:, :3], atol=1e-12)
    np.testing.assert_allclose(traj.t, np.arange(6) / 10.0, atol=1e-12)
    w, x, y, z = traj.quat.T
    angles = np.stack([np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z)),
                       np.arcsin(np.clip(-2 * (x * z - w * y), -1, 1)),
                       np.arctan2(2 * (y * z + w * x), 1 - 2 * (x * x + y * y))], 1)
    wrapped = (angles - est[:, 3:] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(wrapped, 0, atol=1e-9)
    assert ((traj.quat[1:] * traj.quat[:-1]).sum(1) >= 0).all()
    for name in ("result.json", "loss.png", "trajectory.png", "frames.png"):
        assert (tmp_path / "est" / name).is_file()
    from risp_data.figures import png_provenance

    for name in ("loss.png", "trajectory.png", "frames.png"):  # each PNG names the run's seed, as result.json does
        assert png_provenance(tmp_path / "est" / name)["risp:seed"] == str(r["seed"]), name
    saved = json.load(open(tmp_path / "est" / "result.json"))
    assert saved["video"]["sha256"] == r["video"]["sha256"] and len(saved["model"]["sha256"]) == 64
    assert "state_rmse_network" in saved["errors"] and saved["seed"] == 0
    # the sidecar says these are a network's readings of a video (diagnose names their noise: select.estimate_note)
    by = traj.sidecar.get("estimated_by")
    assert by["task"] == "risp-task estimate" and by["model"]["sha256"] == saved["model"]["sha256"]
    assert by["video"]["sha256"] == saved["video"]["sha256"] and by["video"]["frames"] == 6
    # and the run that made them: its seed and settings, as result.json's
    assert by["seed"] == saved["seed"] == 0 and by["config"] == saved["config"] and by["config"]["loss"] == "state"


@pytest.mark.parametrize("task, loss, extra", [
    ("sysid", "oracle", {"lr": 3e-2}),
    # the state loss at lr 1e-2: at 3e-2 RMSProp's first step overshoots and the 6 iterations got back below the start
    # by 8 % (every frame) and 1.5 % (every 2nd) only — a fresh-clone suite run on 2026-11-29 missed it by 0.9 %
    ("sysid", "state", {"lr": 1e-2}),
    ("sysid", "state", {"lr": 1e-2, "every": 2}),  # loss on frames 0, 2, 4 of the simulated timeline
    ("imitate", "state", {}),  # the paper's lr 3e-3 (RMSProp's first steps are ~10× lr)
])
def test_task_lowers_its_loss(quad, tmp_path, task, loss, extra):
    model, video = quad
    kw = dict(model=model, loss=loss, iterations=6, truth=_stem(video) + ".truth.json", plots=False, **extra)
    if task == "sysid":
        kw.update(actions=_stem(video) + ".actions.csv", init="random", seed=1)
    r = _run(task, video, tmp_path / "out", **kw)
    assert len(r["loss"]) == 6 and r["final_loss"] < r["loss"][0], r["loss"]
    assert r["video"]["kept"] == list(range(0, 6, extra.get("every", 1)))
    assert os.path.isfile(tmp_path / "out" / "result.json")
    assert r["config"]["residual"] == ("l1" if task == "sysid" else "l2")  # each task's default, on record
    if task == "imitate":
        assert np.asarray(r["estimates"]["actions"]).shape == (6, 4)
    if task == "sysid" and loss == "oracle":  # against the truth the mass moves towards the true one
        e = r["errors"]
        assert e["parameter_error_final"]["mass"] < e["parameter_error_initial"]["mass"]


def test_random_guess_is_not_the_hidden_truth_of_a_video_with_the_same_seed(quad, tmp_path):
    """make-video --seed 3 draws the hidden mass first from its stream; sysid --init random --seed 3 must not draw
    the same number (until 2026-12-01 both were default_rng(seed), and the guess was the truth to the last bit)."""
    model, video = quad
    truth = json.load(open(_stem(video) + ".truth.json"))
    assert truth["seed"] == 3
    r = _run("sysid", video, tmp_path / "out", model=model, loss="state", iterations=0, init="random", seed=3,
             actions=_stem(video) + ".actions.csv", plots=False)
    guess = r["estimates"]["initial_parameters"]["mass"]
    assert 2.8 <= guess < 3.2 and abs(guess - truth["params"]["mass"]) > 1e-3, (guess, truth["params"]["mass"])


@pytest.mark.parametrize("loss", ["render", "pixelwise", "perceptual"])
def test_render_losses_differentiate_through_renderer_and_network(quad, tmp_path, loss):
    """The image losses run end to end and their gradient reaches the actions: the renders are deterministic
    (seed 0), so the loss after the first step differs from the first only if the step moved the actions.
    (Lowering the loss is not asserted: at 16×16 and 1 spp with a one-epoch network, and the quadrotor's boundary
    terms still biased (tests/test_diff_render.py), six iterations went up and down; docs/tasks.md §Render-mode
    gradients.  The estimates are the best iterate, which may be the initial actions.)"""
    model, video = quad
    r = _run("imitate", video, tmp_path / "out", model=model, loss=loss, iterations=2, spp=1, plots=False)
    assert np.isfinite(r["loss"]).all() and abs(r["loss"][1] - r["loss"][0]) > 1e-9 * abs(r["loss"][0]), r["loss"]
    assert r["final_loss"] == min(r["loss"] + [r["last_loss"]])
    assert r["timings"]["sections_s"]["rendering"] > 0
    # the compared frames are rendered with --spp unless --primal-spp says otherwise; result.json records it
    assert r["config"]["primal_spp"] == 1
    from risp_data.mitsuba_setup import init_mitsuba

    assert r["versions"]["mitsuba_variant"] == init_mitsuba()  # the backend that rendered is on record
    import drjit as dr

    from risp_data.threads import available_cpus

    # the thread counts the arithmetic ran on (render-mode gradients' last bits follow Dr.Jit's): set and on record
    assert r["timings"]["threads"] == {"torch": 1, "drjit": available_cpus()} and dr.thread_count() == available_cpus()
    view = r["view"]  # how much of the vehicle each compared frame shows, before and after (docs/tasks.md §Out of view)
    n = len(view["frames"])
    assert n == 6 and len(view["fraction_in_view_initial"]) == n == len(view["fraction_in_view_final"])
    assert all(0.0 <= v <= 1.0 for v in view["fraction_in_view_final"])
    view_warnings = [w for w in r["warnings"] if "lies beside the video" not in w]  # the --truth hint aside
    assert bool(view_warnings) == bool(view["frames_out_of_view_final"])
    if loss == "perceptual":
        assert r["info"]["perceptual_extractor"] == "filterbank"


def test_a_nan_loss_mid_run_is_a_warning_not_a_lost_run(quad, tmp_path, monkeypatch):
    """A loss that turns NaN at the third iteration (as a step into an unstable simulation would) ends the descent
    with the best iterate kept: the result folder is written, result.json and the warnings say where it stopped."""
    import risp_tasks.tasks.run as run_mod

    real = run_mod.make_loss

    def failing_later(*args, **kwargs):
        loss, calls = real(*args, **kwargs), [0]

        def wrapped(s, n=None):
            calls[0] += 1
            value = loss(s) if n is None else loss(s, n)
            return value * float("nan") if calls[0] == 3 else value
        return wrapped

    monkeypatch.setattr(run_mod, "make_loss", failing_later)
    model, video = quad
    r = _run("sysid", video, tmp_path / "nan", model=model, actions=_stem(video) + ".actions.csv", init="random",
             seed=1, lr=3e-2, iterations=6, plots=False)
    assert len(r["loss"]) == 2 and r["final_loss"] == min(r["loss"]), r["loss"]
    assert "iteration 2" in r["stopped"] and any(w.startswith("optimisation: the loss became NaN") for w in r["warnings"])
    saved = json.load(open(tmp_path / "nan" / "result.json"))
    assert saved["stopped"] == r["stopped"] and saved["last_loss"] is None


def test_warm_start_runs_the_state_loss_before_the_render_loss(quad, tmp_path):
    """--warm-start N: N state-loss iterations (their history recorded apart), then the render loss from where they
    ended; the state loss falls during the warm start and the render descent starts from its end point."""
    model, video = quad
    kw = dict(model=model, actions=_stem(video) + ".actions.csv", truth=_stem(video) + ".truth.json", init="random",
              seed=1, spp=1, plots=False)
    r = _run("sysid", video, tmp_path / "warm", loss="render", iterations=1, warm_start=6, **kw)
    w = r["warm_start"]
    assert w["iterations"] == 6 and len(w["loss"]) == 6 and w["final_loss"] < w["loss"][0], w
    assert len(r["loss"]) == 1
    # the render loss started at the warm start's end: the same as 6 state iterations alone reach
    s = _run("sysid", video, tmp_path / "state", loss="state", iterations=6, **kw)
    assert s["final_loss"] == pytest.approx(w["final_loss"], rel=1e-9)
    assert r["initial"] == s["initial"]  # "initial" stays the random guess, before the warm start


def test_grow_horizon_compares_growing_prefixes_of_the_video(quad, tmp_path):
    """--grow-horizon G: the loss of iteration i compares the first min(T, 2 + (T − 2)·i // G) frames (recorded in
    result.json), and the result is a full-horizon iterate."""
    model, video = quad
    kw = dict(model=model, actions=_stem(video) + ".actions.csv", init="random", seed=1, plots=False)
    r = _run("sysid", video, tmp_path / "grow", loss="state", iterations=6, grow_horizon=4, **kw)
    assert r["frames_compared"] == [2, 3, 4, 5, 6, 6]
    assert r["best_iteration"] in (4, 5, 6)
    plain = _run("sysid", video, tmp_path / "plain", loss="state", iterations=1, **kw)
    # the same start (one seeded guess), but the first loss is that of two frames, not of all six
    assert r["initial"] == plain["initial"] and "frames_compared" not in plain
    assert r["loss"][0] != pytest.approx(plain["loss"][0], rel=1e-6)


@pytest.mark.parametrize("loss", ["state", "pixelwise"])
def test_warm_start_is_for_the_render_loss_only(loss):
    from risp_data.errors import RispError
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RispError, match="--warm-start is for --loss render"):
        TaskConfig(task="sysid", video="v.mp4", loss=loss, warm_start=3)
    with pytest.raises(RispError, match="--warm-start must be >= 0"):
        TaskConfig(task="sysid", video="v.mp4", loss="render", warm_start=-1)


def test_perceptual_loss_is_the_feature_distance(quad):
    """make_loss("perceptual") = mean (F(R(s)) − F(I))², F the filter bank: zero for the frames R(s) itself
    rendered, equal to the hand-computed feature distance for other frames, and it differs from pixelwise."""
    import torch

    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment
    from risp_tasks.tasks.features import feature_extractor
    from risp_tasks.tasks.loop import make_loss

    env = get_environment("quadrotor")
    renderer = StateRenderer("quadrotor", resolution=RES, spp=1)
    s = torch.tensor([[0.0, 0.0, 1.15, 0.2, 0.0, 0.0], [0.05, -0.05, 1.1, -0.4, 0.1, 0.0]], dtype=torch.float64)
    F = feature_extractor(None)
    with torch.no_grad():
        own = renderer(s, seed=0)
        other = renderer(s.flip(0), seed=0)
        loss = make_loss("perceptual", env, [0, 1], None, None, own, renderer=renderer, features=F)
        assert float(loss(s)) == pytest.approx(0.0, abs=1e-12)
        loss = make_loss("perceptual", env, [0, 1], None, None, other, renderer=renderer, features=F)
        expected = ((F(own) - F(other)) ** 2).mean()
        assert float(loss(s)) == pytest.approx(float(expected), rel=1e-5) and float(expected) > 0
        pixel = make_loss("pixelwise", env, [0, 1], None, None, other, renderer=renderer)
        assert float(pixel(s)) != pytest.approx(float(expected), rel=1e-2)


def test_control_reaches_towards_pictured_state(quad, tmp_path):
    from risp_tasks.video import read_video, write_video

    model, video = quad
    goal = tmp_path / "goal"
    write_video(goal, read_video(video).frames[-1:], fps=10)  # a PNG folder with one frame
    pictured = json.load(open(_stem(video) + ".truth.json"))["env_states"][-1]
    (tmp_path / "goal.json").write_text(json.dumps({"env_states": [pictured]}))
    r = _run("control", str(goal / "frame_00000.png"), tmp_path / "ctl", model=model, horizon=3, iterations=5,
             lr=3e-2, plots=True, truth=str(tmp_path / "goal.json"))
    assert r["final_loss"] < r["loss"][0]
    assert np.asarray(r["estimates"]["actions"]).shape == (4, 4)
    assert (tmp_path / "ctl" / "actions.csv").is_file() and (tmp_path / "ctl" / "frames.png").is_file()
    # --truth: the reached state's distance to the pictured one (angles wrapped), before and after
    for when, reached in (("final", r["estimates"]["reached_env_state"]), ("initial", r["initial"]["reached_env_state"])):
        d = np.asarray(reached) - np.asarray(pictured)
        d[3:] = (d[3:] + np.pi) % (2 * np.pi) - np.pi  # yaw, pitch, roll
        assert r["errors"][f"goal_rmse_{when}"] == pytest.approx(float(np.sqrt(np.mean(d ** 2))), rel=1e-9)


def test_control_with_make_videos_whole_truth_aims_at_its_last_state(quad, tmp_path):
    """``--truth`` of a whole make-video run (one row per frame): the pictured state is its last row — for the
    errors, for the oracle loss (which took the first row) and for the plot (which failed on the row count)."""
    from risp_data.envs import get_environment
    from risp_tasks.video import read_video, write_video

    model, video = quad
    write_video(tmp_path / "goal", read_video(video).frames[-1:], fps=10)
    truth_file = _stem(video) + ".truth.json"
    rows = np.asarray(json.load(open(truth_file))["env_states"])
    r = _run("control", str(tmp_path / "goal" / "frame_00000.png"), tmp_path / "ctl", model=model, horizon=3,
             iterations=1, loss="oracle", plots=True, truth=truth_file)
    assert (tmp_path / "ctl" / "trajectory.png").is_file()
    env = get_environment("quadrotor")
    reached = torch.tensor([r["initial"]["reached_env_state"]], dtype=torch.float64)
    for row, equal in ((rows[-1], True), (rows[0], False)):
        d = env.state_to_target(reached) - env.state_to_target(torch.tensor(row[None], dtype=torch.float64))
        assert (r["loss"][0] == pytest.approx(float(d.pow(2).sum()), rel=1e-6)) is equal
    d = np.asarray(r["initial"]["reached_env_state"]) - rows[-1]
    d[3:] = (d[3:] + np.pi) % (2 * np.pi) - np.pi
    assert r["errors"]["goal_rmse_initial"] == pytest.approx(float(np.sqrt(np.mean(d ** 2))), rel=1e-9)


def test_fps_resampling_keeps_the_actions_timeline_and_reads_the_truth_at_the_videos_rate(quad, tmp_path):
    """--fps: the actions file has one row per resampled frame whatever --every keeps (6 frames at 10 fps, --fps 10
    --every 2 kept 3 and asked for 5 rows), and the ground truth, written at the video's own rate, is read at the
    decoded frames the resampling kept (at --fps 5: truth rows 0, 2, 4, not 0, 1, 2)."""
    model, video = quad
    truth_file = _stem(video) + ".truth.json"
    r = _run("estimate", video, tmp_path / "a", model=model, fps=10, every=2, actions=_stem(video) + ".actions.csv",
             iterations=0, plots=False)
    assert r["video"]["frames"] == 6 and r["video"]["kept"] == [0, 2, 4]
    r = _run("estimate", video, tmp_path / "b", model=model, fps=5, truth=truth_file, iterations=0, plots=False)
    assert r["video"]["kept"] == [0, 1, 2] and r["video"]["decoded_kept"] == [0, 2, 4] and r["video"]["fps"] == 5
    true = np.asarray(json.load(open(truth_file))["env_states"])[[0, 2, 4]]
    d = np.asarray(r["estimates"]["env_states"]) - true
    d[:, 3:] = (d[:, 3:] + np.pi) % (2 * np.pi) - np.pi
    assert r["errors"]["state_rmse_final"] == pytest.approx(float(np.sqrt(np.mean(d ** 2))), rel=1e-9)


def test_imitate_as_written_uses_the_most_recent_run(quad, tmp_path, monkeypatch):
    """`risp-task imitate video.mp4` with no options: the newest runs/*/model.pt, named on the first line."""
    import shutil

    from risp_tasks.cli import cli

    model, video = quad
    os.makedirs(tmp_path / "runs" / "old")
    os.makedirs(tmp_path / "runs" / "new")
    shutil.copy(model, tmp_path / "runs" / "old" / "model.pt")
    shutil.copy(model, tmp_path / "runs" / "new" / "model.pt")
    os.utime(tmp_path / "runs" / "old" / "model.pt", (1, 1))
    shutil.copy(video, tmp_path / "video.mp4")
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(cli, ["imitate", "video.mp4", "--iterations", "2", "--quiet", "--no-plots"])
    assert res.exit_code == 0, res.output
    first = res.output.splitlines()[0]
    assert first.startswith("model: ") and os.path.join("runs", "new", "model.pt") in first
    assert os.path.isfile(tmp_path / "results" / "imitate-video-seed0" / "result.json")


@pytest.mark.slow
def test_long_quadrotor_imitation_with_camera_json_and_tracking_init(quad, tmp_path):
    """Paper Sec. 5.5 style: 144 frames at 10 Hz, a camera JSON that is not the environment's camera, the vehicle
    mesh from a file (--mesh; tests/test_tasks_mesh.py checks it is what is drawn), actions
    initialised by the tracking controller along the estimated path (closer to it than hover), then refined."""
    from risp_tasks.tasks.reference import ReferenceConfig, make_reference

    model, _ = quad
    cam = tmp_path / "camera.json"
    cam.write_text(json.dumps({"intrinsics": {"width": 64, "height": 64, "fx": 60.0},
                               "extrinsics": {"origin": [0.3, -2.0, 2.6], "target": [0.0, 0.0, 1.1], "up": [0, 0, 1]}}))
    video = str(tmp_path / "long.mp4")
    mesh = vehicle_obj(tmp_path)
    make_reference(ReferenceConfig(env="quadrotor", out=video, frames=144, resolution=RES, spp=1, camera=str(cam),
                                   mesh=mesh, seed=5, progress=False))
    truth = json.load(open(_stem(video) + ".truth.json"))
    assert len(truth["env_states"]) == 144
    runs = {init: _run("imitate", video, tmp_path / init, model=model, camera=str(cam), mesh=mesh, init=init,
                       iterations=3, plots=False) for init in ("default", "track")}
    assert runs["track"]["loss"][0] < 0.5 * runs["default"]["loss"][0]
    assert runs["track"]["final_loss"] < runs["track"]["loss"][0], runs["track"]["loss"]
    assert np.asarray(runs["track"]["estimates"]["actions"]).shape == (144, 4)


@pytest.mark.parametrize("task", ["sysid", "imitate"])
def test_hand_tasks_lower_their_loss(tmp_path_factory, tmp_path, task):
    """The hand: five stiffnesses / five finger torques, joint angles and rates from the first two frames."""
    model, video = shared_model(tmp_path_factory, "hand"), shared_video(tmp_path_factory, "hand")
    kw = dict(model=model, loss="oracle", truth=_stem(video) + ".truth.json", iterations=5, plots=False)
    if task == "sysid":
        kw.update(actions=_stem(video) + ".actions.csv", lr=3e-2)
    r = _run(task, video, tmp_path / "out", **kw)
    assert r["final_loss"] < r["loss"][0], r["loss"]
    assert len(r["estimates"]["parameters"]) == 5  # imitate identifies them by default on the hand (fits_params)
    if task == "imitate":
        assert np.asarray(r["estimates"]["actions"]).shape == (6, 5)
        assert len(r["info"]["fitted_parameters"]) == 5


def test_imitate_with_action_knots_optimises_a_piecewise_linear_command(tmp_path_factory, tmp_path):
    """--action-knots 3 on the hand's 6 frames: the optimised commands lie on 3 knots' piecewise-linear curve (zero
    second differences inside each of its two pieces, not at the middle knot), the loss falls, and the start is the
    same random draw as without knots, projected onto the knots."""
    from risp_tasks.tasks.imitate import knot_basis

    model, video = shared_model(tmp_path_factory, "hand"), shared_video(tmp_path_factory, "hand")
    kw = dict(model=model, loss="oracle", truth=_stem(video) + ".truth.json", iterations=5, plots=False,
              init="random", seed=4)
    r = _run("imitate", video, tmp_path / "knots", action_knots=3, **kw)
    assert r["final_loss"] < r["loss"][0], r["loss"]
    u = np.asarray(r["estimates"]["actions"])  # (6, 5); knots at frames 0, 2.5, 5
    assert u.shape == (6, 5)
    second = u[2:] - 2 * u[1:-1] + u[:-2]  # frames 1..4; the curve bends between frames 2 and 3 only
    assert np.abs(second[[0, 3]]).max() < 1e-9 and np.abs(second[[1, 2]]).max() > 1e-6
    plain = _run("imitate", video, tmp_path / "plain", iterations=0, **{k: v for k, v in kw.items() if k != "iterations"})
    x0 = np.asarray(plain["estimates"]["initial_actions"])
    W = knot_basis(6, 3).numpy()
    projected = W @ np.linalg.lstsq(W, x0, rcond=None)[0]
    assert np.allclose(r["estimates"]["initial_actions"], projected, atol=1e-9)


def test_imitate_chooses_its_knots_by_cross_validation(tmp_path_factory, tmp_path):
    """--action-knots auto on the hand's 6 frames: every candidate K is scored on held-out frames, the one with the
    smallest held-out loss is the one fitted (its commands lie on K knots' curve, or one row per frame), the start is
    the same random draw as a plain run's, and a fixed K's fit of the same configuration ends where the chosen one does."""
    from risp_tasks.tasks.imitate import knot_candidates

    model, video = shared_model(tmp_path_factory, "hand"), shared_video(tmp_path_factory, "hand")
    kw = dict(model=model, loss="state", iterations=5, plots=False, init="random", seed=4)
    r = _run("imitate", video, tmp_path / "auto", action_knots="auto", **kw)
    sel = r["info"]["knot_selection"]
    assert sel["candidates"] == knot_candidates(6) == [2, 4, 6]
    assert len(sel["held_out_loss"]) == 3 and all(np.isfinite(sel["held_out_loss"]))
    assert len(set(sel["held_out_loss"])) == 3  # each candidate was fitted, not one score copied
    best = int(np.argmin(sel["held_out_loss"]))
    assert sel["chosen"] == sel["candidates"][best]
    assert r["config"]["action_knots"] == "auto"
    fixed = _run("imitate", video, tmp_path / "fixed", action_knots=0 if sel["chosen"] == 6 else sel["chosen"], **kw)
    # the same fit; torch's CPU sums may differ in the last bit from one run to the next (seen: 1 ulp)
    assert np.allclose(r["estimates"]["actions"], fixed["estimates"]["actions"], rtol=1e-12, atol=1e-12)
    assert r["info"]["parametrisation"] == fixed["info"]["parametrisation"]
    plain = _run("imitate", video, tmp_path / "plain", **{**kw, "iterations": 0, "action_knots": 0})
    W_start = np.asarray(fixed["estimates"]["initial_actions"])
    assert np.allclose(r["estimates"]["initial_actions"], W_start, atol=1e-12)
    if sel["chosen"] == 6:
        assert np.allclose(r["estimates"]["initial_actions"], plain["estimates"]["initial_actions"], atol=1e-12)


def test_imitate_on_the_hand_chooses_its_knots_unless_told(tmp_path_factory, tmp_path):
    """Unset --action-knots on the hand's imitate (state loss): the knots are chosen by cross-validation, recorded
    and said in the command's words, and the result is --action-knots auto's; --action-knots 0 keeps one row per frame
    and chooses nothing."""
    from risp_tasks.tasks.config import TaskConfig
    from risp_tasks.tasks.run import run_task

    model, video = shared_model(tmp_path_factory, "hand"), shared_video(tmp_path_factory, "hand")
    kw = dict(model=model, loss="state", iterations=3, plots=False, init="random", seed=4)
    said = []
    default = run_task(TaskConfig(task="imitate", video=video, out=str(tmp_path / "default"), progress=False, **kw),
                       echo=said.append)
    assert default["config"]["action_knots"] is None
    sel = default["info"]["knot_selection"]
    assert sel["candidates"] == [2, 4, 6] and len(sel["held_out_loss"]) == 3
    line = next(s for s in said if "chosen by cross-validation" in s)
    assert "--action-knots 0 for one row per frame" in line and "held-out loss by K" in line
    auto = _run("imitate", video, tmp_path / "auto", action_knots="auto", **kw)
    # the same fits; torch's CPU sums may differ in the last bit from one run to the next (seen: 1 ulp)
    assert np.allclose(default["estimates"]["actions"], auto["estimates"]["actions"], rtol=1e-12, atol=1e-12)
    assert default["info"]["knot_selection"]["held_out_loss"] == pytest.approx(
        auto["info"]["knot_selection"]["held_out_loss"], rel=1e-12)
    assert default["info"]["knot_selection"]["chosen"] == auto["info"]["knot_selection"]["chosen"]
    rows = _run("imitate", video, tmp_path / "rows", action_knots=0, **kw)
    assert "knot_selection" not in rows["info"] and rows["info"]["parametrisation"] == "one row per frame"


@pytest.mark.parametrize("env, extra, knots", [
    ("hand", {}, "auto"), ("hand", {"loss": "render"}, "auto"),  # imitate's default on the hand
    ("quadrotor", {}, 0), ("rod", {}, 0),  # not measured there: one row per frame
    ("hand", {"loss": "oracle", "truth": "t.json"}, 0), ("hand", {"loss": "pixelwise"}, 0),  # auto refuses these
    ("hand", {"loss": "perceptual"}, 0),
    ("hand", {"task": "control"}, 0),  # one pictured state: no frames to hold out
    ("hand", {"action_knots": 0}, 0), ("hand", {"action_knots": 8}, 8),  # a given number is kept
    ("quadrotor", {"action_knots": "auto"}, "auto"), ("quadrotor", {"init": "track"}, 0),
])
def test_imitate_chooses_knots_by_default_on_the_hand_alone(env, extra, knots):
    from risp_tasks.tasks.config import TaskConfig
    from risp_tasks.tasks.imitate import knots_setting

    cfg = TaskConfig(**{"task": "imitate", "video": "goal.png" if extra.get("task") == "control" else "v.mp4",
                        **extra})
    assert knots_setting(cfg, env) == knots


def test_action_knots_auto_is_imitates_alone():
    from risp_data.errors import RispError
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RispError, match="--action-knots auto is imitate's"):
        TaskConfig(task="control", video="goal.png", action_knots="auto")
    with pytest.raises(RispError, match="--action-knots auto chooses how the commands"):
        TaskConfig(task="imitate", video="v.mp4", action_knots="auto", init="track")
    with pytest.raises(RispError, match="a whole number"):
        TaskConfig(task="imitate", video="v.mp4", action_knots="often")
    for loss in ("pixelwise", "perceptual", "oracle"):  # a baseline must not choose by the network's readings
        with pytest.raises(RispError, match=f"with --loss {loss} give a number"):
            TaskConfig(task="imitate", video="v.mp4", action_knots="auto", loss=loss, truth="t.json")
    assert TaskConfig(task="imitate", video="v.mp4", action_knots="auto", loss="render").action_knots == "auto"
    with pytest.raises(RispError, match="--action-knots is for imitate and control"):
        TaskConfig(task="sysid", video="v.mp4", action_knots="auto")


def test_imitate_with_the_l1_residual_records_it_and_descends(tmp_path_factory, tmp_path):
    """--residual l1 through the whole task: the same start has another loss than with l2 (absolute, not squared,
    differences to N's readings), the l1 loss falls, and result.json records the residual."""
    model, video = shared_model(tmp_path_factory, "hand"), shared_video(tmp_path_factory, "hand")
    kw = dict(model=model, loss="state", iterations=5, plots=False, init="random", seed=2, action_knots=0)
    l1 = _run("imitate", video, tmp_path / "l1", residual="l1", **kw)
    l2 = _run("imitate", video, tmp_path / "l2", **kw)
    assert l1["final_loss"] < l1["loss"][0], l1["loss"]
    assert l1["errors"] == {} and l1["estimates"]["initial_actions"] == l2["estimates"]["initial_actions"]
    assert l1["loss"][0] != pytest.approx(l2["loss"][0], rel=1e-3)
    assert json.load(open(tmp_path / "l1" / "result.json"))["config"]["residual"] == "l1"
    assert l2["config"]["residual"] == "l2"


def test_imitate_simulates_the_given_parameters(tmp_path_factory, tmp_path):
    """--params: imitate simulates the video's own stiffnesses (here the truth file's; a sysid result.json gives the
    same values), records them, and the same zero commands then roll out differently from the nominal hand's."""
    model, video = shared_model(tmp_path_factory, "hand"), shared_video(tmp_path_factory, "hand")
    truth = json.load(open(_stem(video) + ".truth.json"))
    stiff = {n: v for n, v in truth["params"].items() if n.startswith("stiffness_")}
    kw = dict(model=model, loss="oracle", truth=_stem(video) + ".truth.json", iterations=0, plots=False)
    nominal = _run("imitate", video, tmp_path / "nominal", fit_params=False, **kw)
    given = _run("imitate", video, tmp_path / "given", params=json.dumps(stiff), **kw)
    assert "fitted_parameters" not in given["info"]  # given parameters are not identified again by default
    assert all(given["info"]["parameters"][n] == pytest.approx(v) for n, v in stiff.items())
    assert nominal["info"]["parameters"]["stiffness_index"] == 1.0
    assert given["errors"]["state_rmse_initial"] != pytest.approx(nominal["errors"]["state_rmse_initial"], rel=1e-3)
    sysid_like = tmp_path / "result.json"
    sysid_like.write_text(json.dumps({"task": "sysid", "estimates": {"parameters": stiff}}))
    again = _run("imitate", video, tmp_path / "again", params=str(sysid_like), **kw)
    assert again["errors"]["state_rmse_initial"] == pytest.approx(given["errors"]["state_rmse_initial"], rel=1e-12)


def test_imitate_fit_params_moves_the_parameters_with_the_commands(tmp_path_factory, tmp_path):
    """--fit-params: the hand's five stiffnesses are variables beside the commands.  They start from the middle
    of their ranges (the same rollout as --params of those values), or from the values --params gives; the loss
    falls, they move and stay inside their ranges, and the result reports them, their errors against the truth
    file, and can be given back to --params."""
    model, video = shared_model(tmp_path_factory, "hand"), shared_video(tmp_path_factory, "hand")
    truth_file = _stem(video) + ".truth.json"
    kw = dict(model=model, loss="oracle", truth=truth_file, plots=False)
    fit = _run("imitate", video, tmp_path / "fit", fit_params=True, iterations=5, lr=3e-2, **kw)
    names = [f"stiffness_{f}" for f in ("thumb", "index", "middle", "ring", "little")]
    start, end = fit["estimates"]["initial_parameters"], fit["estimates"]["parameters"]
    assert list(start) == names and all(start[n] == pytest.approx(0.5) for n in names)
    assert fit["info"]["fitted_parameters"] == names and fit["info"]["parameters"]["stiffness_index"] == pytest.approx(0.5)
    assert fit["final_loss"] < fit["loss"][0], fit["loss"]
    assert all(0 <= end[n] <= 1 for n in names) and max(abs(end[n] - 0.5) for n in names) > 1e-3
    truth = json.load(open(truth_file))["params"]
    assert fit["errors"]["parameter_error_final"] == {n: pytest.approx(abs(end[n] - truth[n])) for n in names}
    middle = _run("imitate", video, tmp_path / "middle", params=json.dumps({n: 0.5 for n in names}), iterations=0, **kw)
    assert fit["errors"]["state_rmse_initial"] == pytest.approx(middle["errors"]["state_rmse_initial"], rel=1e-12)
    given = _run("imitate", video, tmp_path / "given", fit_params=True, iterations=0,
                 params=json.dumps({"stiffness_index": 0.2, "stiffness_ring": 7.0}), **kw)
    assert given["estimates"]["initial_parameters"] == {**{n: pytest.approx(0.5) for n in names},
                                                        "stiffness_index": pytest.approx(0.2), "stiffness_ring": pytest.approx(1.0)}
    back = _run("imitate", video, tmp_path / "back", params=str(tmp_path / "fit" / "result.json"), iterations=0, **kw)
    assert back["info"]["parameters"] == {**back["info"]["parameters"], **{n: pytest.approx(end[n]) for n in names}}


@pytest.mark.parametrize("task, extra, words", [
    ("sysid", {}, "--fit-params is for imitate"),
    ("imitate", {"init": "track"}, "--init track optimises the controller's reference path"),
])
def test_fit_params_is_for_imitate_with_its_commands_as_variables(task, extra, words):
    from risp_data.errors import RispError
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RispError, match=words):
        TaskConfig(task=task, video="v.mp4", fit_params=True, **extra)


@pytest.mark.parametrize("env, extra, fits", [
    ("hand", {}, True), ("rod", {}, True), ("quadrotor", {}, False),  # the default per environment
    ("hand", {"params": '{"stiffness_index": 0.3}'}, False),  # given parameters are kept
    ("rod", {"init": "track"}, False),  # a reference path, not commands, is optimised
    ("hand", {"task": "control"}, False),  # control reaches a state; imitate's default is imitate's
    ("quadrotor", {"fit_params": True}, True), ("rod", {"fit_params": False}, False),  # the flags decide
])
def test_imitate_identifies_the_parameters_by_default_where_they_shape_the_motion(env, extra, fits):
    from risp_tasks.tasks.config import TaskConfig
    from risp_tasks.tasks.imitate import fits_params

    cfg = TaskConfig(**{"task": "imitate", "video": "v.mp4", **extra})
    assert fits_params(cfg, env) is fits


def test_knot_basis_interpolates_linearly_between_its_knots():
    """W's rows sum to 1, W reproduces a linear function of the frame index exactly, equals the knot values at
    the knots' frames, and is the identity without knots (K = 0) or with a knot per frame."""
    from risp_tasks.tasks.imitate import knot_basis

    W = knot_basis(21, 5).numpy()  # knots at frames 0, 5, 10, 15, 20
    assert W.shape == (21, 5) and np.allclose(W.sum(1), 1)
    z = np.array([0.3, -1.0, 2.0, 0.5, 0.0])
    assert np.allclose((W @ z)[[0, 5, 10, 15, 20]], z)
    assert np.allclose((W @ z)[7], z[1] + 0.4 * (z[2] - z[1]))
    knots_t = np.arange(5) * 5.0
    assert np.allclose(W @ (2 - 0.1 * knots_t), 2 - 0.1 * np.arange(21))
    assert np.array_equal(knot_basis(6, 0).numpy(), np.eye(6)) and np.array_equal(knot_basis(6, 6).numpy(), np.eye(6))


def test_reference_flight_compensates_a_steady_wind(tmp_path):
    """make-video's flight controller has an integral term: under a hidden 3 N wind the vehicle returns to its
    path (the recorded thrusts carry the compensation) instead of settling F / (m·KP) ≈ 0.25 m downwind, which
    would leave the sampled flight volume.  Same seed with and without wind: late in the flight the positions
    agree to a few centimetres, and the thrust vectors differ (the commands tilt into the wind)."""
    from risp_tasks.tasks.reference import ReferenceConfig, make_reference

    runs = {}
    for name, effect in (("calm", None), ("wind", "wind:3,0,0")):
        out = str(tmp_path / f"{name}.mp4")
        make_reference(ReferenceConfig(env="quadrotor", out=out, frames=120, fps=10, resolution=4, spp=1, seed=2,
                                       effect=effect, progress=False))
        runs[name] = json.load(open(_stem(out) + ".truth.json"))
    calm, wind = (np.asarray(runs[n]["env_states"])[:, :3] for n in ("calm", "wind"))
    assert np.abs(wind[-30:] - calm[-30:]).max() < 0.05, np.abs(wind - calm).max(0)
    assert np.abs(wind - calm).max() > 0.02  # the wind did push it before the integral caught up
    assert np.abs(np.subtract(runs["wind"]["actions"], runs["calm"]["actions"])).max() > 0.05


def test_loading_a_model_leaves_the_global_torch_stream_alone(quad):
    """The network's default initialisation (overwritten by the checkpoint) must not consume the caller's
    random numbers: a task's seeded draws are then the same whether or not a model was loaded first."""
    import torch

    from risp_train.predictor import load

    torch.manual_seed(5)
    expected = torch.rand(3)
    torch.manual_seed(5)
    load(quad[0])
    assert torch.equal(torch.rand(3), expected)


def test_the_network_reads_a_video_in_batches_with_the_numbers_of_one_batch(quad, tmp_path, monkeypatch):
    """N read every frame of a video in one call (its activations grew with the video's length): batches of
    PREDICT_BATCH frames now, whose readings equal one call's on all frames; the task reads in such batches."""
    from risp_train.predictor import RispPredictor, load

    import risp_tasks.tasks.run as run_mod
    from risp_tasks.video import read_video

    model, video = quad
    predictor = load(model)
    frames = torch.from_numpy(read_video(video, resolution=RES).frames)
    with torch.no_grad():
        whole = predictor.predict(frames)
    for got, expected in zip(run_mod.predict_frames(predictor, frames, batch=4, progress=False), whole):
        assert got.shape == expected.shape and torch.allclose(got, expected, rtol=0, atol=1e-6)
    sizes, predict = [], RispPredictor.predict

    def spy(self, images):
        sizes.append(len(images))
        return predict(self, images)

    monkeypatch.setattr(run_mod, "PREDICT_BATCH", 4)
    monkeypatch.setattr(RispPredictor, "predict", spy)
    result = _run("estimate", video, tmp_path / "o", model=model, iterations=0, plots=False)
    assert sizes[:2] == [4, 2]  # the video's 6 frames in two batches
    assert np.allclose(result["estimates"]["env_states"], whole[0].double().numpy(), atol=1e-6)


def test_outside_sampled_states_counts_frames_beyond_the_training_box():
    """Which frames leave the sampler's box, per state; the boundary itself (the cube on the floor), and up to 1 %
    of a state's range beyond it, is inside."""
    from risp_data.envs import get_environment
    from risp_tasks.tasks.reference import outside_sampled_states, outside_warning

    env = get_environment("cube")
    lo, hi = np.asarray(env.state_low), np.asarray(env.state_high)
    mid = (lo + hi) / 2
    S = np.tile(mid, (10, 1))
    S[:3, 0] = hi[0] + 0.1  # x beyond the box in 3 frames
    S[2:4, 2] = lo[2] - 0.01  # z below it in 2 (one of them also x)
    S[5, 2] = lo[2]  # resting exactly on the floor: inside
    S[6, 2] = lo[2] - 0.004  # pressed 4 mm into the floor by the penalty contact: within 1 % of z's range, inside
    o = outside_sampled_states("cube", S)
    assert o["fraction"] == pytest.approx(0.4) and o["states"] == {"x": pytest.approx(0.3), "z": pytest.approx(0.2)}
    assert o["low"] == pytest.approx(lo.tolist()) and o["high"] == pytest.approx(hi.tolist())
    line = outside_warning(o)
    assert line.startswith("warning: 40 % of the frames") and "x 30 %, z 20 %" in line and "\n" not in line
    inside = outside_sampled_states("cube", np.tile(mid, (4, 1)))
    assert inside == {**inside, "fraction": 0.0, "states": {}} and outside_warning(inside) is None


def test_make_video_records_and_warns_when_a_flight_leaves_the_training_box(tmp_path):
    """make-video writes the check into the truth file and prints the warning line (a quadrotor flight whose
    tracking controller overshoots the sampled x range: seed 8); the video itself is written as before."""
    from click.testing import CliRunner

    from risp_tasks.cli import cli
    from risp_tasks.tasks.reference import OUTSIDE_TOLERANCE

    out = tmp_path / "flight.mp4"
    res = CliRunner().invoke(cli, ["make-video", "--env", "quadrotor", "--out", str(out), "--frames", "20", "--fps",
                                   "10", "--resolution", "16", "--spp", "1", "--seed", "8", "--quiet"])
    assert res.exit_code == 0, res.output
    truth = json.load(open(tmp_path / "flight.truth.json"))
    o = truth["outside_sampled_states"]
    x = np.asarray(truth["env_states"])[:, 0]
    beyond = OUTSIDE_TOLERANCE * (o["high"][0] - o["low"][0])
    assert 0 < o["fraction"] <= 1 and o["states"]["x"] == pytest.approx(np.mean(np.abs(x) > o["high"][0] + beyond))
    assert out.exists() and "warning: " in res.output and "% of the frames have states outside" in res.output


@pytest.mark.parametrize("frames", [2, 8, 20])
def test_cube_tosses_stay_inside_the_training_box(frames):
    """A reference toss slides on a frictionless floor with a constant horizontal velocity aimed at a point inside
    the sampler's x, y range, so no frame of any seed leaves the box the networks are trained on (before, 65–85 %
    of a 20-frame toss's frames did, up to 1.3 m out); the toss still moves and spins."""
    from risp_tasks.tasks.reference import ReferenceConfig, _motion, _params, outside_sampled_states
    from risp_tasks.tasks.simulate import timeline

    for seed in range(6):
        rng = np.random.default_rng(seed)
        sim, k = timeline("cube", 10.0, ())
        p = _params(ReferenceConfig(env="cube", out=""), sim, rng, None, None)
        full, actions = _motion(sim, p, frames, k, 10.0, rng)
        S = sim.to_env_state(full).numpy()
        assert actions is None and S.shape == (frames, 6)
        assert outside_sampled_states("cube", S)["fraction"] == 0.0, (seed, S[:, :3])
        assert np.abs(full[0, 7:9].numpy()).max() > 0 and np.abs(full[0, 10:13].numpy()).max() > 0


def test_toss_velocity_aims_inside_and_is_capped():
    """toss_velocity: the segment xy0 + v·T ends at u·(XY_RANGE − TOSS_MARGIN); a short toss is capped at
    TOSS_SPEED per component and then ends between its start and that point."""
    from risp_data.envs.cube import XY_RANGE
    from risp_tasks.tasks.reference import TOSS_MARGIN, TOSS_SPEED, toss_velocity

    xy0, u = np.array([0.1, -0.15]), np.array([-1.0, 0.5])
    end = u * (XY_RANGE - TOSS_MARGIN)
    v = toss_velocity(xy0, u, 1.9)
    assert np.allclose(xy0 + v * 1.9, end)
    v_short = toss_velocity(xy0, u, 0.1)
    assert np.abs(v_short).max() == pytest.approx(TOSS_SPEED) and np.all(np.abs(v_short) <= TOSS_SPEED + 1e-12)
    stop = xy0 + v_short * 0.1
    assert np.all((stop - xy0) * (end - stop) >= 0)  # between start and aim, component-wise


def test_make_reference_gives_the_callers_thread_counts_back(tmp_path):
    """make_reference set one torch thread and Dr.Jit to every CPU and left them so: the tables call it in-process,
    between cells that must each run on one Dr.Jit thread."""
    import drjit as dr

    from risp_data.mitsuba_setup import init_mitsuba
    from risp_tasks.tasks.reference import ReferenceConfig, make_reference

    init_mitsuba()
    torch_before, drjit_before = torch.get_num_threads(), dr.thread_count()
    try:
        torch.set_num_threads(3)
        dr.set_thread_count(1)
        truth = make_reference(ReferenceConfig(env="quadrotor", out=str(tmp_path / "v.mp4"), frames=2, resolution=8,
                                               spp=1, seed=1, progress=False))
        assert truth["threads"]["torch"] == 1 and truth["threads"]["drjit"] >= 1  # what it ran with, recorded
        assert torch.get_num_threads() == 3 and dr.thread_count() == 1
    finally:
        torch.set_num_threads(torch_before)
        dr.set_thread_count(drjit_before)


def test_bound_warnings_name_a_parameter_held_at_an_end_of_its_range():
    """A parameter the projection holds on an end of its range gets one line saying which end and that the figure
    is a bound; one inside the range gets none."""
    from risp_tasks.tasks.run import bound_warnings

    est = {"parameters": {"mass": 2.8, "log10_E": 7.0, "stiffness_thumb": 0.3},
           "ranges": {"mass": [2.8, 3.2], "log10_E": [4.0, 7.0], "stiffness_thumb": [0.0, 1.0]}}
    lines = bound_warnings(est)
    assert len(lines) == 2 and all("\n" not in s for s in lines)
    assert lines[0].startswith("mass = 2.8 ended on the lower end of its range [2.8, 3.2]") and "bound" in lines[0]
    assert lines[1].startswith("log10_E = 7 ended on the upper end of its range [4, 7]")
    assert bound_warnings({"parameters": {"mass": 2.9}, "ranges": {"mass": [2.8, 3.2]}}) == []
    assert bound_warnings({"estimates": {}}) == [] and bound_warnings({}) == []


def test_sysid_driven_onto_a_range_end_says_so(quad, tmp_path, monkeypatch):
    """With a mass range wholly below the video's (2.8–3.2 kg), the fit against the true states (oracle loss) ends on
    the range's upper end: result.json's warnings and the command's last lines say so; the echo of an estimate
    with no iterations says what was read, not 'loss A -> A in 0 iterations'."""
    from risp_tasks.cli import cli
    from risp_tasks.tasks import sysid

    model, video = quad
    monkeypatch.setattr(sysid, "parameter_ranges", lambda sim: {"mass": (2.0, 2.2)})
    args = ["sysid", video, "--model", model, "--actions", _stem(video) + ".actions.csv", "--loss", "oracle",
            "--truth", _stem(video) + ".truth.json", "--lr", "0.1", "--iterations", "10", "--no-plots", "--quiet",
            "--out", str(tmp_path / "s")]
    out = CliRunner().invoke(cli, args, catch_exceptions=False).output
    r = json.loads((tmp_path / "s" / "result.json").read_text())
    assert r["estimates"]["ranges"]["mass"] == [2.0, 2.2] and r["estimates"]["parameters"]["mass"] == 2.2
    said = [w for w in r["warnings"] if w.startswith("mass = ") and "end of its range" in w]
    assert len(said) == 1 and "upper end" in said[0] and f"warning: {said[0]}" in out, out
    est = CliRunner().invoke(cli, ["estimate", video, "--model", model, "--no-plots", "--quiet",
                                   "--out", str(tmp_path / "e")], catch_exceptions=False).output
    assert "6 frames read by the network; results:" in est and "0 iterations" not in est, est
