"""Bad input to the task commands (issue 10 §Bad input): one clear line naming the file and the problem,
non-zero exit, and no result folder (not even a half-written one)."""

import json
import os
import time
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from tasks_helpers import shared_model, shared_video

pytest.importorskip("av")
pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def quad(tmp_path_factory):
    return shared_model(tmp_path_factory, "quadrotor"), shared_video(tmp_path_factory, "quadrotor")


def _invoke(args, tmp_path):
    from risp_tasks.cli import cli

    res = CliRunner().invoke(cli, args + ["--out", str(tmp_path / "res"), "--quiet", "--iterations", "1", "--no-plots"])
    line = _error_line(res, skip="model: ")  # the tasks name the model they loaded before failing
    assert not (tmp_path / "res").exists()
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")]
    return line


def _error_line(res, skip: str | None = None):
    """The one `Error:` line of a failed CLI run (lines starting with ``skip`` aside)."""
    lines = [ln for ln in res.output.splitlines() if ln.strip() and not (skip and ln.startswith(skip))]
    assert res.exit_code != 0 and len(lines) == 1 and lines[0].startswith("Error: "), res.output
    return lines[0]


def _actions(video):
    return os.path.splitext(video)[0] + ".actions.csv"


def test_missing_video(quad, tmp_path):
    line = _invoke(["sysid", str(tmp_path / "nope.mp4"), "--model", quad[0]], tmp_path)
    assert "nope.mp4" in line and "no such file" in line


def test_non_video_and_zero_byte_files(quad, tmp_path):
    (tmp_path / "notes.mp4").write_text("these are notes, not a video\n" * 50)
    line = _invoke(["estimate", str(tmp_path / "notes.mp4"), "--model", quad[0]], tmp_path)
    assert "notes.mp4" in line and "cannot decode" in line
    (tmp_path / "zero.mp4").write_bytes(b"")
    line = _invoke(["estimate", str(tmp_path / "zero.mp4"), "--model", quad[0]], tmp_path)
    assert "zero.mp4" in line and "empty" in line
    (tmp_path / "frames").mkdir()
    line = _invoke(["estimate", str(tmp_path / "frames"), "--model", quad[0]], tmp_path)
    assert "frames" in line and "no .png frames" in line


def test_actions_disagree_with_video_length(quad, tmp_path):
    model, video = quad
    rows = open(_actions(video)).read().splitlines()
    (tmp_path / "short.csv").write_text("\n".join(rows[:-2]) + "\n")
    line = _invoke(["sysid", video, "--model", model, "--actions", str(tmp_path / "short.csv")], tmp_path)
    assert "short.csv" in line and "4 action rows but the video has 6 frames" in line


def test_actions_wrong_width_and_nan(quad, tmp_path):
    model, video = quad
    (tmp_path / "narrow.csv").write_text("t,f0,f1\n" + "".join(f"{i/10},1,1\n" for i in range(6)))
    line = _invoke(["sysid", video, "--model", model, "--actions", str(tmp_path / "narrow.csv")], tmp_path)
    assert "narrow.csv" in line and "missing f2,f3" in line
    rows = open(_actions(video)).read().splitlines()
    rows[3] = rows[3].rsplit(",", 1)[0] + ",nan"
    (tmp_path / "nan.csv").write_text("\n".join(rows) + "\n")
    line = _invoke(["sysid", video, "--model", model, "--actions", str(tmp_path / "nan.csv")], tmp_path)
    assert "nan.csv" in line and "NaN" in line and "f3" in line
    rows = open(_actions(video)).read().splitlines()  # a fifth motor column: a file for another system
    wide = [rows[0] + ",f4"] + [r + ",1.0" for r in rows[1:]]
    (tmp_path / "wide.csv").write_text("\n".join(wide) + "\n")
    line = _invoke(["sysid", video, "--model", model, "--actions", str(tmp_path / "wide.csv")], tmp_path)
    assert "wide.csv" in line and "unexpected column(s) f4" in line and "t,f0,f1,f2,f3" in line
    assert b"\r" not in open(_actions(video), "rb").read()  # written with plain newlines
    # thrusts in other units (×1000: grams?) were clamped by the simulator without a word
    head, *body = open(_actions(video)).read().splitlines()
    big = [head] + [",".join([r.split(",")[0]] + [str(float(x) * 1000) for x in r.split(",")[1:]]) for r in body]
    (tmp_path / "big.csv").write_text("\n".join(big) + "\n")
    line = _invoke(["sysid", video, "--model", model, "--actions", str(tmp_path / "big.csv")], tmp_path)
    assert "big.csv: rotor thrusts up to" in line and "above the 25 N the simulated rotors can give" in line


def test_actions_from_a_spreadsheet_read_as_written():
    """A UTF-8 byte-order mark (Excel's "CSV UTF-8") and a blank last line are not errors: the file reads as the
    plain one; a blank line is no row (the count check still applies)."""
    import tempfile

    from risp_data.errors import RispError
    from risp_tasks.tasks.inputs import read_actions

    plain = "t,f0,f1,f2,f3\n" + "".join(f"{i / 10},{i},1,2,3\n" for i in range(3))
    with tempfile.TemporaryDirectory() as d:
        ref = os.path.join(d, "plain.csv")
        open(ref, "w").write(plain)
        expected = read_actions(ref, "quadrotor", 3)
        for name, data in (("bom.csv", "\ufeff" + plain), ("blank.csv", plain + "\n"), ("crlf.csv", plain.replace("\n", "\r\n"))):
            path = os.path.join(d, name)
            open(path, "w", encoding="utf-8", newline="").write(data)
            assert np.array_equal(read_actions(path, "quadrotor", 3), expected), name
        with pytest.raises(RispError, match="2 action rows but the video has 3 frames"):
            open(path, "w").write("t,f0,f1,f2,f3\n0,1,1,1,1\n\n0.1,1,1,1,1\n\n")
            read_actions(path, "quadrotor", 3)


def test_model_for_another_environment(quad, tmp_path):
    model, video = quad
    line = _invoke(["imitate", video, "--model", model, "--env", "hand"], tmp_path)
    assert "model.pt" in line and "'quadrotor', not 'hand'" in line


@pytest.mark.parametrize("change, words", [
    (dict(env="pendulum"), "trained for environment 'pendulum', which risp does not know"),
    (dict(state_names=["x", "y", "z", "roll", "pitch", "yaw"]), "state names ['x', 'y', 'z', 'roll', 'pitch', 'yaw'] differ"),
    (dict(target_names=[f"t{i}" for i in range(9)]), "target names ['t0', 't1', 't2', 't3', 't4', 't5', 't6', 't7', "
                                                      "'t8'] differ from the quadrotor's"),
    # fewer names than the network's outputs: refused when the checkpoint is read, before the layout is compared
    (dict(target_names=["t0", "t1"]), "normalization target_mean has 9 entries, the checkpoint has 2 target_names"),
])
def test_model_of_another_state_layout_is_refused(quad, tmp_path, change, words):
    """A checkpoint whose environment or state/target names are not risp's (another system, an older state layout)
    is one line naming the model file — it was read as the environment's states, or failed deep inside a task."""
    import torch

    from risp_train.checkpoint import save_checkpoint

    model, video = quad
    ckpt = torch.load(model, map_location="cpu", weights_only=True)
    save_checkpoint(str(tmp_path / "other.pt"), {**ckpt, **change})
    line = _invoke(["estimate", video, "--model", str(tmp_path / "other.pt")], tmp_path)
    assert "other.pt" in line and words in line, line


def test_corrupt_model_file(quad, tmp_path):
    (tmp_path / "model.pt").write_bytes(b"\x00garbage")
    line = _invoke(["imitate", quad[1], "--model", str(tmp_path / "model.pt")], tmp_path)
    assert "corrupt or unreadable checkpoint" in line and "model.pt" in line


def test_model_given_as_its_run_folder(quad, tmp_path):
    """``--model runs/NAME`` names the run folder's model.pt; a folder without one is one line saying why."""
    import shutil

    from risp_train import load
    from risp_train.checkpoint import model_file

    model, video = quad
    run = os.path.dirname(model)
    assert os.path.samefile(model_file(run), model) and load(run).env_name == "quadrotor"
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    shutil.copy(model, unfinished / "last.pt")
    line = _invoke(["imitate", video, "--model", str(unfinished)], tmp_path)
    assert "unfinished is a folder without a model.pt" in line and "has not finished" in line
    (tmp_path / "empty").mkdir()
    line = _invoke(["imitate", video, "--model", str(tmp_path / "empty")], tmp_path)
    assert "empty is a folder without a model.pt" in line and "has not finished" not in line


def test_no_trained_model_under_runs(quad, tmp_path, monkeypatch):
    """No runs/ folder at all (a fresh checkout), a --runs folder that does not exist, and an empty runs/: each one
    line saying which, and how to get a model."""
    monkeypatch.chdir(tmp_path)
    line = _invoke(["imitate", quad[1]], tmp_path)
    assert "no folder runs/ here" in line and "risp-train fit" in line and "--model" in line
    line = _invoke(["imitate", quad[1], "--runs", "nosuch"], tmp_path)
    assert "no folder nosuch/ here" in line
    (tmp_path / "runs").mkdir()
    line = _invoke(["imitate", quad[1]], tmp_path)
    assert "no trained model under runs/" in line and "risp-train fit SHARDS` (it writes runs/" in line


def test_camera_json_with_missing_keys(quad, tmp_path):
    model, video = quad
    (tmp_path / "cam.json").write_text(json.dumps({"intrinsics": {"width": 64, "height": 64},
                                                   "extrinsics": {"origin": [0, -2, 2], "target": [0, 0, 1]}}))
    line = _invoke(["imitate", video, "--model", model, "--camera", str(tmp_path / "cam.json")], tmp_path)
    assert "cam.json" in line and "intrinsics.fx" in line
    (tmp_path / "cam2.json").write_text("{not json")
    line = _invoke(["imitate", video, "--model", model, "--camera", str(tmp_path / "cam2.json")], tmp_path)
    assert "cam2.json" in line and "not valid JSON" in line


def test_perceptual_weights_file_missing_or_not_vgg(quad, tmp_path):
    model, video = quad
    line = _invoke(["imitate", video, "--model", model, "--loss", "perceptual", "--perceptual-weights",
                    str(tmp_path / "vgg.pth")], tmp_path)
    assert "vgg.pth" in line and "perceptual weights file not found" in line
    (tmp_path / "junk.pth").write_bytes(b"not a state dict")
    line = _invoke(["imitate", video, "--model", model, "--loss", "perceptual", "--perceptual-weights",
                    str(tmp_path / "junk.pth")], tmp_path)
    assert "junk.pth" in line and "not a torchvision vgg16 state dict" in line


def test_cube_has_no_actions_to_imitate(tmp_path_factory, tmp_path, monkeypatch):
    """Said before a frame is decoded (a long video used to be read, with its progress bar, first)."""
    from risp_tasks.tasks import run

    model = shared_model(tmp_path_factory, "cube")
    video = shared_video(tmp_path_factory, "cube")

    def decoded(*args, **kwargs):
        raise AssertionError("the video was decoded before the error")

    monkeypatch.setattr(run, "_reference", decoded)
    line = _invoke(["imitate", video, "--model", model], tmp_path)
    assert "cube has no actions" in line and "most recent" not in line


def test_a_most_recent_model_for_another_system_is_named(quad, tmp_path_factory, tmp_path, monkeypatch):
    """Without --model the newest run under runs/ is used: when it is a cube model and the video a quadrotor's,
    imitate and sysid --actions say that the chosen model is the cube's (not that the actions file is wrong), and a
    --truth file of another system is refused."""
    import shutil

    _, video = quad
    (tmp_path / "runs" / "cube-run").mkdir(parents=True)
    shutil.copy(shared_model(tmp_path_factory, "cube"), tmp_path / "runs" / "cube-run" / "model.pt")
    monkeypatch.chdir(tmp_path)
    stem = os.path.splitext(video)[0]
    # make-video's own file names its system in its comment tag: the mismatch is said at once
    line = _invoke(["imitate", video], tmp_path)
    assert "a quadrotor video (make-video's tag in the file), but the model is a cube model" in line
    assert "is a cube model: give --model" in line
    # footage without the tag (the same frames, written again): the actions or the truth file tell
    from risp_tasks.video import read_video, write_video

    plain = str(tmp_path / "plain.mp4")
    write_video(plain, read_video(video).frames, fps=10)
    line = _invoke(["imitate", plain], tmp_path)
    assert "the cube has no actions to imitate" in line and "is a cube model: give --model" in line
    line = _invoke(["sysid", plain, "--actions", stem + ".actions.csv"], tmp_path)
    assert "the cube has no actions" in line and "is a cube model: give --model" in line
    line = _invoke(["estimate", plain, "--truth", stem + ".truth.json"], tmp_path)
    assert "ground truth of a quadrotor video, but the model is a cube model" in line


def test_without_model_the_newest_run_of_the_video_s_system_is_used(quad, tmp_path_factory, tmp_path, monkeypatch):
    """runs/ holds an older quadrotor run and a newer cube run: a make-video quadrotor file (its tag names the
    system) is read with the quadrotor run, and the first line says why that one; so is --env quadrotor on untagged
    footage. (Before, the newest run was taken whatever its system, and the task stopped at the mismatch.)"""
    import shutil

    from risp_tasks.cli import cli
    from risp_tasks.video import read_video, write_video

    model, video = quad
    for name, src, age in (("quad-run", model, 100), ("cube-run", shared_model(tmp_path_factory, "cube"), 0)):
        (tmp_path / "runs" / name).mkdir(parents=True)
        shutil.copy(src, tmp_path / "runs" / name / "model.pt")
        t = time.time() - age
        os.utime(tmp_path / "runs" / name / "model.pt", (t, t))
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(cli, ["estimate", video, "--out", str(tmp_path / "a"), "--quiet", "--no-plots"])
    assert res.exit_code == 0, res.output
    first = res.output.splitlines()[0]
    assert "quad-run" in first and "the most recent quadrotor model under runs/, for the video's system" in first
    plain = str(tmp_path / "plain.mp4")
    write_video(plain, read_video(video).frames, fps=10)
    res = CliRunner().invoke(cli, ["estimate", plain, "--env", "quadrotor", "--out", str(tmp_path / "b"), "--quiet",
                                   "--no-plots"])
    assert res.exit_code == 0 and "quad-run" in res.output.splitlines()[0] and "for --env" in res.output, res.output
    res = CliRunner().invoke(cli, ["estimate", plain, "--out", str(tmp_path / "c"), "--quiet", "--no-plots"])
    assert "cube-run" in res.output.splitlines()[0]  # untagged and no --env: the newest run, as before


def test_existing_result_folder_is_not_overwritten(quad, tmp_path):
    model, video = quad
    (tmp_path / "res").mkdir()
    (tmp_path / "res" / "keep.txt").write_text("mine")
    from risp_tasks.cli import cli

    base = ["estimate", video, "--model", model, "--out", str(tmp_path / "res"), "--quiet", "--no-plots"]
    res = CliRunner().invoke(cli, base)
    assert res.exit_code != 0 and "exists" in res.output and "--overwrite" in res.output
    assert (tmp_path / "res" / "keep.txt").read_text() == "mine"
    # --overwrite replaces only a task's result folder (one with result.json), not a folder of the user's
    res = CliRunner().invoke(cli, base + ["--overwrite"])
    assert res.exit_code != 0 and "is not a task's result folder" in res.output, res.output
    assert (tmp_path / "res" / "keep.txt").read_text() == "mine"
    (tmp_path / "res" / "keep.txt").unlink()
    (tmp_path / "res").rmdir()
    assert CliRunner().invoke(cli, base + ["--seed", "1"]).exit_code == 0
    res = CliRunner().invoke(cli, base + ["--seed", "2", "--overwrite"])
    assert res.exit_code == 0, res.output
    assert json.load(open(tmp_path / "res" / "result.json"))["seed"] == 2
    assert sorted(os.listdir(tmp_path)) == ["res"]  # the old folder went, no temporaries stayed


CPU_OOM = ("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: you tried to "
           "allocate 3221225472 bytes. Error code 12 (Cannot allocate memory)")


@pytest.mark.parametrize("error, words", [
    (RuntimeError(CPU_OOM), "out of memory (tried to allocate 3 GiB) while running estimate on"),
    (torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of 79 GiB"),
     "out of GPU memory (tried to allocate 2.00 GiB) while running estimate on"),
])
def test_running_out_of_memory_in_a_task_is_one_line(quad, tmp_path, monkeypatch, error, words):
    """torch's out-of-memory errors mid-task (a RuntimeError on the CPU, torch.OutOfMemoryError on a GPU) were a
    traceback: one line saying what ran out and what to lower, and no result folder."""
    import risp_tasks.tasks.run as run_mod

    def oom(*a, **k):
        raise error

    monkeypatch.setattr(run_mod, "optimize", oom)
    line = _invoke(["estimate", quad[1], "--model", quad[0]], tmp_path)
    assert words in line and "--every or --fps" in line and "--spp" in line, line


def test_running_out_of_memory_in_make_video_is_one_line(tmp_path, monkeypatch):
    import risp_tasks.tasks.reference as reference
    from risp_tasks.cli import cli

    def oom(*a, **k):
        raise RuntimeError(CPU_OOM)

    monkeypatch.setattr(reference, "_motion", oom)
    res = CliRunner().invoke(cli, ["make-video", "--env", "quadrotor", "--frames", "2", "--quiet",
                                   "--out", str(tmp_path / "v.mp4")])
    line = _error_line(res)
    assert "out of memory (tried to allocate 3 GiB) while making" in line and "--frames, --resolution or --spp" in line
    assert not os.listdir(tmp_path)


def test_failure_mid_run_leaves_no_result_folder(quad, tmp_path, monkeypatch):
    """An exception while writing the results removes the temporary folder."""
    import risp_tasks.tasks.run as run

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(run, "plot_loss", boom)
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RuntimeError):
        run.run_task(TaskConfig(task="estimate", video=quad[1], model=quad[0], out=str(tmp_path / "r"), progress=False),
                     echo=lambda s: None)
    assert os.listdir(tmp_path) == []


def test_unknown_gradient_boundary_term(quad, tmp_path):
    """`--gradient` takes flat|mitsuba: another name stops before anything is read or written."""
    from risp_tasks.cli import cli

    res = CliRunner().invoke(cli, ["sysid", quad[1], "--model", quad[0], "--loss", "render", "--gradient", "smooth",
                                   "--out", str(tmp_path / "res"), "--quiet"])
    assert res.exit_code == 2, res.output
    assert "--gradient" in res.output and "'flat'" in res.output and "'mitsuba'" in res.output
    assert not (tmp_path / "res").exists()


def test_warm_start_with_another_loss_is_one_error_line(quad, tmp_path):
    """`--warm-start` runs the state loss before the render loss: with any other loss it stops, one line."""
    line = _invoke(["sysid", quad[1], "--model", quad[0], "--actions", os.path.splitext(quad[1])[0] + ".actions.csv",
                    "--loss", "state", "--warm-start", "5"], tmp_path)
    assert "--warm-start is for --loss render" in line


def test_grow_horizon_outside_sysid_and_imitate_is_one_error_line(quad, tmp_path):
    """`--grow-horizon` grows the compared frames of a video: `estimate` (no optimisation) refuses it, one line."""
    line = _invoke(["estimate", quad[1], "--model", quad[0], "--grow-horizon", "5"], tmp_path)
    assert "--grow-horizon is for sysid and imitate" in line


def test_action_knots_with_the_tracking_init_is_one_error_line(quad, tmp_path):
    """`--init track` optimises the controller's reference path, not the commands: knots on them are refused."""
    line = _invoke(["imitate", quad[1], "--model", quad[0], "--init", "track", "--action-knots", "4"], tmp_path)
    assert "--action-knots parametrises the commands themselves" in line


def test_more_action_knots_than_action_rows_is_one_error_line(quad, tmp_path):
    """K knots over fewer frames fell back to one row per frame while result.json said K: refused, one line —
    imitate against the video's 6 frames, control against --horizon + 1 rows before any work."""
    line = _invoke(["imitate", quad[1], "--model", quad[0], "--action-knots", "7"], tmp_path)
    assert "--action-knots 7 is more than the 6 action rows" in line, line
    from risp_data.errors import RispError
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RispError, match=r"--action-knots 5 is more than the 4 action rows of --horizon 3"):
        TaskConfig(task="control", video="goal.png", horizon=3, action_knots=5)
    assert TaskConfig(task="control", video="goal.png", horizon=3, action_knots=4).action_knots == 4


@pytest.mark.parametrize("args, expected", [
    (["--action-knots", "often"], "--action-knots must be a whole number (0, or >= 2) or auto, got 'often'"),
    (["--action-knots", "auto", "--init", "track"], "--action-knots auto chooses how the commands are parametrised"),
])
def test_bad_action_knots_are_one_error_line(quad, tmp_path, args, expected):
    """`--action-knots` takes a number or `auto`: anything else, or auto with the tracking controller, one line."""
    line = _invoke(["imitate", quad[1], "--model", quad[0], *args], tmp_path)
    assert expected in line, line


def test_imitate_with_an_unknown_parameter_is_one_error_line(quad, tmp_path):
    """`--params` names the quadrotor's parameters: a misspelt one stops imitate with the known names, one line."""
    line = _invoke(["imitate", quad[1], "--model", quad[0], "--params", '{"mas": 3.0}'], tmp_path)
    assert "unknown quadrotor parameter 'mas'" in line and "mass" in line


def test_residual_options_are_checked(quad, tmp_path):
    """`--residual` takes l2|l1 (click's usage error names both), and l1 with an image loss is one error line."""
    from risp_tasks.cli import cli

    res = CliRunner().invoke(cli, ["sysid", quad[1], "--model", quad[0], "--residual", "huber",
                                   "--out", str(tmp_path / "res"), "--quiet"])
    assert res.exit_code == 2 and "'l2'" in res.output and "'l1'" in res.output, res.output
    assert not (tmp_path / "res").exists()
    line = _invoke(["sysid", quad[1], "--model", quad[0], "--actions", _actions(quad[1]), "--loss", "pixelwise",
                    "--residual", "l1"], tmp_path)
    assert "--residual l1 is for the render, state and oracle losses" in line


def test_negative_seed_is_one_error_line(quad, tmp_path):
    model, video = quad
    line = _invoke(["sysid", video, "--model", model, "--seed", "-1"], tmp_path)
    assert "--seed must be >= 0" in line


@pytest.mark.parametrize("content,words", [({"state": ["up", "down"]}, "'state' must be a list of numbers"),
                                           ({"env_state": [[0.0, 1.0], [2.0]]}, "'env_state' must be a list of numbers"),
                                           ({"env_state": [0.0, 0.0]}, "'env_state' must have 6 entries, got 2")])
def test_control_initial_state_that_is_not_a_state(quad, tmp_path, content, words):
    from risp_tasks.video import read_video, write_video

    model, video = quad
    write_video(tmp_path / "goal", read_video(video).frames[-1:], fps=10)
    (tmp_path / "s0.json").write_text(json.dumps(content))
    line = _invoke(["control", str(tmp_path / "goal" / "frame_00000.png"), "--model", model,
                    "--initial-state", str(tmp_path / "s0.json")], tmp_path)
    assert "s0.json" in line and words in line, line


def test_control_warns_of_an_initial_state_outside_the_trained_range(quad, tmp_path):
    from risp_tasks.cli import cli
    from risp_tasks.video import read_video, write_video

    model, video = quad
    write_video(tmp_path / "goal", read_video(video).frames[-1:], fps=10)
    (tmp_path / "s0.json").write_text(json.dumps({"env_state": [5.0, 0.0, 1.1, 0.0, 0.0, 0.0]}))
    res = CliRunner().invoke(cli, ["control", str(tmp_path / "goal" / "frame_00000.png"), "--model", model,
                                   "--initial-state", str(tmp_path / "s0.json"), "--horizon", "1", "--loss", "state",
                                   "--out", str(tmp_path / "res"), "--quiet", "--iterations", "1", "--no-plots"])
    assert res.exit_code == 0, res.output
    assert "warning: " + str(tmp_path / "s0.json") + ": the initial state's x lie(s) outside" in res.output
    result = json.loads((tmp_path / "res" / "result.json").read_text())
    assert any("the initial state's x lie(s) outside" in w for w in result["warnings"])


@pytest.mark.parametrize("params,words", [('{"mass": "heavy"}', "'mass' must be a finite number"),
                                          ('{"mass": [3.0]}', "'mass' must be a finite number"),
                                          ('{"mass": NaN}', "'mass' must be a finite number"),
                                          ("[3.0]", "must be a JSON object")])
def test_make_video_params_that_are_not_numbers(tmp_path, params, words):
    from risp_tasks.cli import cli

    out = tmp_path / "v.mp4"
    res = CliRunner().invoke(cli, ["make-video", "--env", "quadrotor", "--out", str(out), "--frames", "2",
                                   "--resolution", "8", "--params", params, "--quiet"])
    assert words in _error_line(res)
    assert not out.exists() and not [p for p in os.listdir(tmp_path) if p != "v.mp4"]


def test_rod_initial_state_cannot_be_sensor_heights(tmp_path):
    """initial_sim_state starts the rod at rest whatever its sensor heights: refuse them rather than ignore them."""
    from risp_data.errors import RispError
    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.control import read_initial_state

    (tmp_path / "s0.json").write_text(json.dumps({"env_state": [0.1] * 10}))
    with pytest.raises(RispError, match="cannot be given as 'env_state'"):
        read_initial_state(str(tmp_path / "s0.json"), get_simulator("rod"))
    rest = get_simulator("rod").default_state(1)
    (tmp_path / "full.json").write_text(json.dumps({"state": rest[0].tolist()}))
    assert read_initial_state(str(tmp_path / "full.json"), get_simulator("rod")).shape == (1, 360)


def test_make_video_does_not_replace_a_video_unasked(tmp_path):
    """An existing video (or its ground truth) at --out: one error line naming it, the files untouched; with
    --overwrite the same command replaces all three (another seed, another truth)."""
    from risp_tasks.cli import cli

    out = tmp_path / "v.mp4"
    args = ["make-video", "--env", "quadrotor", "--out", str(out), "--frames", "2", "--resolution", "8", "--quiet"]
    first = CliRunner().invoke(cli, args + ["--seed", "1"])
    assert first.exit_code == 0 and "actions " in first.output, first.output
    before = {p: (tmp_path / p).read_bytes() for p in ("v.mp4", "v.truth.json", "v.actions.csv")}
    line = _error_line(CliRunner().invoke(cli, args + ["--seed", "2"]))
    assert "v.mp4: exists" in line and "--overwrite" in line
    assert all((tmp_path / p).read_bytes() == b for p, b in before.items())
    (tmp_path / "v.mp4").unlink()  # the truth alone still belongs to a video: refused too
    assert "v.truth.json: exists" in _error_line(CliRunner().invoke(cli, args + ["--seed", "2"]))
    res = CliRunner().invoke(cli, args + ["--seed", "2", "--overwrite"])
    assert res.exit_code == 0, res.output
    truth = json.load(open(tmp_path / "v.truth.json"))
    from risp_tasks.video import sha256_file

    assert truth["seed"] == 2 and truth["video_sha256"] == sha256_file(out) and truth["versions"]["torch"]
    # a cube video (no actions) over the quadrotor's: the quadrotor's actions file does not stay beside it
    cube = ["make-video", "--env", "cube", "--out", str(out), "--frames", "2", "--resolution", "8", "--quiet"]
    assert CliRunner().invoke(cli, cube + ["--overwrite"]).exit_code == 0
    assert json.load(open(tmp_path / "v.truth.json"))["env"] == "cube" and not (tmp_path / "v.actions.csv").exists()


@pytest.mark.parametrize("suffix", [".mp4", ""])
def test_make_video_does_not_replace_a_video_another_process_wrote_meanwhile(tmp_path, monkeypatch, suffix):
    """Two make-video runs to one --out both passed the "exists" check before rendering, and the second silently
    replaced the first; its truth hashed the file then on disk (possibly the other run's video).  Now the video is
    published only where nothing is by then, and the truth names the bytes this run wrote."""
    import risp_tasks.video as video
    from risp_tasks.cli import cli

    out = tmp_path / f"v{suffix}"
    other = np.full((2, 8, 8, 3), 0.3, np.float32)
    real = video.write_video

    def meanwhile(path, *a, **kw):  # another make-video publishes its video while this one renders
        real(path, other, 10)
        return real(path, *a, **kw)

    monkeypatch.setattr(video, "write_video", meanwhile)
    args = ["make-video", "--env", "quadrotor", "--out", str(out), "--frames", "2", "--resolution", "8", "--quiet"]
    line = _error_line(CliRunner().invoke(cli, args))
    # a file: refused when it is published; a folder of frames already by write_video's own look at the path
    assert ("exists (written by another process" if suffix else "folder exists and is not empty") in line
    assert np.allclose(video.read_video(out).frames, video.read_video(out).frames[:1]) and not (
        tmp_path / "v.truth.json").exists()  # the other run's frames stay; no truth of this run beside them
    monkeypatch.setattr(video, "write_video", real)
    assert CliRunner().invoke(cli, args + ["--overwrite"]).exit_code == 0
    truth = json.load(open(tmp_path / "v.truth.json"))
    assert truth["video_sha256"] == video.sha256_file(out)


def test_write_video_returns_the_hash_of_what_it_wrote(tmp_path):
    from risp_tasks.video import sha256_file, write_video

    frames = np.full((2, 8, 8, 3), 0.4, np.float32)
    for path in (tmp_path / "a.mp4", tmp_path / "frames"):
        assert write_video(path, frames, 10, exclusive=True) == sha256_file(path)
        with pytest.raises(FileExistsError):
            write_video(path, frames * 0.5, 10, overwrite=True, exclusive=True)
        assert write_video(path, frames * 0.5, 10, overwrite=True) == sha256_file(path)


def test_a_video_replaced_while_a_task_reads_it_is_refused(tmp_path, monkeypatch):
    """A task hashed the video after decoding it: a video renamed into the path in between gave the result the
    other video's checksum (and a truth check against the wrong file)."""
    import risp_tasks.tasks.inputs as inputs
    from risp_data.errors import RispError
    from risp_tasks.video import write_video

    path = tmp_path / "v.mp4"
    write_video(path, np.full((3, 8, 8, 3), 0.2, np.float32), 10)
    real = inputs.read_video

    def then_replaced(p, **kw):
        frames = real(p, **kw)
        write_video(p, np.full((3, 8, 8, 3), 0.6, np.float32), 10)
        return frames

    monkeypatch.setattr(inputs, "read_video", then_replaced)
    with pytest.raises(RispError, match="the video changed while it was read"):
        inputs.read_reference(str(path), 8, 1, None, None)
    monkeypatch.setattr(inputs, "read_video", real)
    assert inputs.read_reference(str(path), 8, 1, None, None).sha256 == inputs.sha256_file(str(path))


def _deny_writes_in(monkeypatch, folder):
    """os.access says no write permission on ``folder`` (as a read-only mount would; the tests may run as root,
    for whom chmod does not take writing away)."""
    import risp_data.atomic as atomic

    real = os.access
    monkeypatch.setattr(atomic.os, "access", lambda p, mode, **k: False if (os.path.abspath(p) == str(folder)
                                                                            and mode & os.W_OK) else real(p, mode, **k))


def test_an_out_that_cannot_be_written_is_refused_before_the_work(quad, tmp_path, monkeypatch):
    """A task and make-video whose --out lies in a folder they cannot write say so at once, naming --out — they
    used to optimise (render) everything and then fail naming a `.tmp-*` folder."""
    import risp_tasks.tasks.run as run_mod
    from risp_tasks.cli import cli

    locked = tmp_path / "locked"
    locked.mkdir()
    _deny_writes_in(monkeypatch, locked)
    monkeypatch.setattr(run_mod, "optimize", lambda *a, **k: pytest.fail("optimised before checking --out"))
    res = CliRunner().invoke(cli, ["estimate", quad[1], "--model", quad[0], "--out", str(locked / "res"), "--quiet"])
    line = _error_line(res, skip="model: ")
    assert f"--out {locked / 'res'}: its folder" in line and "no write permission" in line, line
    import risp_data.render as render_mod

    monkeypatch.setattr(render_mod, "Renderer", lambda *a, **k: pytest.fail("rendered before checking --out"))
    for out in ("v.mp4", "frames"):
        res = CliRunner().invoke(cli, ["make-video", "--env", "quadrotor", "--frames", "2", "--quiet",
                                       "--out", str(locked / out)])
        assert "no write permission" in _error_line(res)
    assert os.listdir(locked) == []


def test_make_video_refuses_a_truth_path_that_is_a_folder_before_rendering(tmp_path, monkeypatch):
    """The truth and actions files are written after the video: a folder in their place is refused before any
    rendering (the new video was written and then no truth could be, leaving a video without its truth)."""
    import risp_data.render as render_mod
    from risp_tasks.cli import cli

    (tmp_path / "y.truth.json").mkdir()
    monkeypatch.setattr(render_mod, "Renderer", lambda *a, **k: pytest.fail("rendered before checking"))
    res = CliRunner().invoke(cli, ["make-video", "--env", "quadrotor", "--frames", "2", "--quiet", "--overwrite",
                                   "--out", str(tmp_path / "y.mp4")])
    line = _error_line(res)
    assert "y.truth.json: exists and is not a file (the video's ground truth file goes there)" in line, line
    assert sorted(os.listdir(tmp_path)) == ["y.truth.json"]


def test_make_video_refuses_an_out_that_is_a_folder_before_rendering(tmp_path, monkeypatch):
    """--out v.mp4 where v.mp4 is a folder: refused before the render (with --overwrite it rendered every frame and
    then failed to publish the file; without it the line called the folder a reference video's file)."""
    import risp_data.render as render_mod
    from risp_tasks.cli import cli

    (tmp_path / "v.mp4").mkdir()
    monkeypatch.setattr(render_mod, "Renderer", lambda *a, **k: pytest.fail("rendered before checking --out"))
    for extra in ([], ["--overwrite"]):
        res = CliRunner().invoke(cli, ["make-video", "--env", "quadrotor", "--frames", "2", "--quiet", *extra,
                                       "--out", str(tmp_path / "v.mp4")])
        line = _error_line(res)
        assert "v.mp4: an existing folder, not a video file" in line, line
    assert os.listdir(tmp_path) == ["v.mp4"] and not os.listdir(tmp_path / "v.mp4")


def test_make_video_refuses_a_suffix_it_cannot_write(tmp_path):
    """--out v.gif is one line before any rendering, not a folder of PNGs named v.gif."""
    from risp_tasks.cli import cli

    args = ["make-video", "--env", "quadrotor", "--out", str(tmp_path / "v.gif"), "--frames", "2", "--quiet"]
    line = _error_line(CliRunner().invoke(cli, args))
    assert "v.gif: cannot write .gif videos" in line and ".mp4" in line
    assert not os.listdir(tmp_path)
    # a folder of the user's files is refused before rendering too, even with --overwrite
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "notes.txt").write_text("mine")
    args = ["make-video", "--env", "quadrotor", "--out", str(tmp_path / "frames"), "--frames", "2", "--quiet",
            "--overwrite"]
    import risp_data.render as render_mod

    def no_render(*a, **k):
        raise AssertionError("rendered before the output was checked")

    orig, render_mod.Renderer = render_mod.Renderer, no_render
    try:
        line = _error_line(CliRunner().invoke(cli, args))
    finally:
        render_mod.Renderer = orig
    assert "frames: holds files other than PNG frames" in line
    # a folder name with a dot (not a media suffix) is a PNG folder, as before
    args = ["make-video", "--env", "quadrotor", "--out", str(tmp_path / "clip-1.5"), "--frames", "2", "--res", "8",
            "--quiet"]
    assert CliRunner().invoke(cli, args).exit_code == 0
    assert sorted(os.listdir(tmp_path / "clip-1.5")) == ["frame_00000.png", "frame_00001.png"]
    # its frames carry make-video's tag, as a video file's comment does: the tasks read the system from it
    from risp_tasks.tasks.run import video_system
    from risp_tasks.video import read_video

    assert read_video(tmp_path / "clip-1.5", source_fps=10).comment == "risp make-video env=quadrotor seed=0"
    assert video_system(str(tmp_path / "clip-1.5")) == "quadrotor"


def test_png_folder_is_replaced_only_with_overwrite_and_only_if_all_png(tmp_path):
    from risp_data.errors import RispError
    from risp_tasks.video import read_video, write_video

    folder = tmp_path / "frames"
    write_video(folder, np.full((3, 8, 8, 3), 0.2, np.float32), fps=10)
    with pytest.raises(RispError, match="folder exists and is not empty"):
        write_video(folder, np.full((2, 8, 8, 3), 0.7, np.float32), fps=10)
    write_video(folder, np.full((2, 8, 8, 3), 0.7, np.float32), fps=10, overwrite=True)
    video = read_video(folder, source_fps=10)
    assert len(video.frames) == 2 and np.allclose(video.frames, 0.7, atol=0.01)
    assert sorted(os.listdir(tmp_path)) == ["frames"]  # no temporaries left
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(RispError, match="holds files other than PNG frames"):
        write_video(folder, np.full((2, 8, 8, 3), 0.1, np.float32), fps=10, overwrite=True)
    assert (folder / "notes.txt").read_text() == "mine" and len(os.listdir(folder)) == 3


def test_truth_of_another_video_is_refused(quad, tmp_path):
    """make-video's truth names its video by checksum: a truth beside another video is one line, not errors measured
    against the wrong motion."""
    model, video = quad
    truth = json.load(open(os.path.splitext(video)[0] + ".truth.json"))
    truth["video_sha256"] = "0" * 64
    (tmp_path / "other.truth.json").write_text(json.dumps(truth))
    line = _invoke(["estimate", video, "--model", model, "--truth", str(tmp_path / "other.truth.json")], tmp_path)
    assert "other.truth.json: the ground truth of another video" in line


@pytest.mark.parametrize("change, words", [(dict(frames=999), "the ground truth of a 999-frame video"),
                                           (dict(fps=30), "the ground truth of a 30 fps video")])
def test_a_truth_without_checksum_must_match_the_videos_timeline(quad, tmp_path, change, words):
    """A truth file from before video_sha256 was compared row by row with any video (exit 0): its frame count and
    rate must at least be the video's."""
    model, video = quad
    truth = json.load(open(os.path.splitext(video)[0] + ".truth.json"))
    del truth["video_sha256"]
    truth.update(change)
    (tmp_path / "old.truth.json").write_text(json.dumps(truth))
    line = _invoke(["estimate", video, "--model", model, "--truth", str(tmp_path / "old.truth.json")], tmp_path)
    assert "old.truth.json: " + words in line


def test_estimate_without_actions_and_an_unused_camera_say_so(quad, tmp_path):
    """estimate without --actions writes a CSV diagnose refuses (no command columns), and --camera with the state
    loss changes nothing: both are said in the result's warnings (printed as `warning:` lines at the end)."""
    from risp_tasks.cli import cli

    model, video = quad
    (tmp_path / "cam.json").write_text(json.dumps({"intrinsics": {"width": 64, "height": 64, "fx": 60.0},
                                                   "extrinsics": {"origin": [0, -2, 2], "target": [0, 0, 1],
                                                                  "up": [0, 0, 1]}}))
    res = CliRunner().invoke(cli, ["estimate", video, "--model", model, "--camera", str(tmp_path / "cam.json"),
                                   "--out", str(tmp_path / "res"), "--quiet", "--no-plots"])
    assert res.exit_code == 0, res.output
    warnings = json.load(open(tmp_path / "res" / "result.json"))["warnings"]
    assert any("without --actions the trajectory CSV has no command columns" in w for w in warnings), warnings
    assert any("--camera is used where the task renders" in w for w in warnings), warnings
    assert "warning: without --actions" in res.output
    # and diagnose's reader says what the file lacks and how to get it
    from risp_data.errors import RispError
    from risp_tasks.measured import read_trajectory

    with pytest.raises(RispError, match=r"missing column\(s\) f0, f1, f2, f3: an estimate made without --actions; "
                                        r"make it again with --actions A.csv"):
        read_trajectory(tmp_path / "res" / "trajectory.csv", "quadrotor")


def test_make_video_params_with_a_huge_integer(tmp_path):
    from risp_tasks.cli import cli

    res = CliRunner().invoke(cli, ["make-video", "--env", "quadrotor", "--out", str(tmp_path / "v.mp4"), "--frames",
                                   "2", "--resolution", "8", "--params", '{"mass": 1' + "0" * 400 + "}", "--quiet"])
    assert "'mass' must be a finite number" in _error_line(res)


def test_sysid_prints_the_parameter_error_and_a_kept_start(quad, tmp_path):
    """With --truth the printed summary gives the identified parameter's error (as result.json has it); when no
    step improved on the start (here a step size that overshoots), a note says the start was kept."""
    from risp_tasks.cli import cli

    model, video = quad
    base = ["sysid", video, "--model", model, "--actions", _actions(video), "--truth",
            os.path.splitext(video)[0] + ".truth.json", "--quiet", "--no-plots", "--iterations", "3"]
    res = CliRunner().invoke(cli, base + ["--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    result = json.load(open(tmp_path / "a" / "result.json"))
    saved = result["errors"]["parameter_error_final"]["mass"]
    from risp_tasks.video import sha256_file

    assert result["inputs"]["actions"]["sha256"] == sha256_file(_actions(video)) and set(result["inputs"]) == {"actions", "truth"}
    assert f"mass error = {saved:.4g}" in res.output, res.output
    res = CliRunner().invoke(cli, base + ["--out", str(tmp_path / "b"), "--lr", "100", "--optimizer", "sgd"])
    kept = json.load(open(tmp_path / "b" / "result.json"))["best_iteration"] == 0
    assert res.exit_code == 0 and kept == ("note: no step improved on the start" in res.output), res.output
    assert kept, "an SGD step of 100 was expected to overshoot"


@pytest.mark.parametrize("option,value,words", [("--frames", "1", "--frames must be >= 2, got 1"),
                                                ("--fps", "0", "--fps must be > 0, got 0.0"),
                                                ("--seed", "-3", "--seed must be >= 0, got -3")])
def test_make_video_names_the_one_bad_setting(tmp_path, option, value, words):
    from risp_tasks.cli import cli

    args = ["make-video", "--env", "quadrotor", "--out", str(tmp_path / "v.mp4"), "--frames", "2", "--resolution", "8",
            "--quiet", option, value]
    line = _error_line(CliRunner().invoke(cli, args))
    assert words in line and line.count("must be") == 1
    assert not os.listdir(tmp_path)


@pytest.mark.parametrize("intrinsics,extrinsics,words", [
    ({"width": 64, "height": 64, "fx": 60.0}, {"origin": [0, 0, 3], "target": [0, 0, 1], "up": [0, 0, 1]},
     "parallel to the viewing direction"),
    ({"width": 64, "height": 64, "fx": 60.0}, {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 0]},
     "is zero or parallel"),
    ({"width": 64, "height": "tall", "fx": 60.0}, {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 1]},
     "must be numbers"),
    ({"width": True, "height": 64, "fx": 60.0}, {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 1]},
     "must be numbers"),
    ({"width": 64, "height": -5, "fx": 60.0}, {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 1]},
     "finite width, height and fx > 0"),
    ({"width": 64, "height": 64, "fx": 1e-9}, {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 1]},
     "field of view"),
    ({"width": 64, "height": 64, "fx": 60.0, "cx": 10}, {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 1]},
     "intrinsics.cx = 10 is off the image centre"),
    # each of these was accepted (exit 0) and the value taken or ignored without a word
    ({"width": "64", "height": 64, "fx": 60.0}, {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 1]},
     "must be numbers, not strings"),
    ({"width": 64, "height": 64, "fx": 60.0, "fy": 30.0}, {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 1]},
     "only square pixels"),
    ({"width": 64, "height": 64, "fx": 60.0, "distortion": [0.3, 0.1, 0, 0]},
     {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 1]}, "lens distortion is not modelled"),
    ({"width": 64, "height": 64, "fx": 60.0},
     {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 1], "rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]},
     "extrinsics.rotation is not part of the camera model"),
])
def test_camera_json_with_impossible_geometry(quad, tmp_path, intrinsics, extrinsics, words):
    """Each used to pass the checks: an undefined roll rendered NaN frames (blamed on the frames, or a flat grey
    strip and the start as the result), a height that was never read, a JSON true taken for 1 pixel."""
    model, video = quad
    (tmp_path / "cam.json").write_text(json.dumps({"intrinsics": intrinsics, "extrinsics": extrinsics}))
    line = _invoke(["imitate", video, "--model", model, "--camera", str(tmp_path / "cam.json")], tmp_path)
    assert "cam.json" in line and words in line, line


def test_camera_aspect_ratio_and_unused_keys(tmp_path):
    """A 640×480 camera fits a 640×480 video and a square one (make-video --camera writes the centre square), not a
    portrait one; a key without geometry ("name") is listed as not used, not refused."""
    from risp_data.errors import RispError
    from risp_tasks.tasks.inputs import read_camera

    cam = {"intrinsics": {"width": 640, "height": 480, "fx": 590.0, "name": "front"},
           "extrinsics": {"origin": [0, -1.7, 2.9], "target": [0, 0, 1.15], "up": [0, 0, 1]}}
    (tmp_path / "c.json").write_text(json.dumps(cam))
    notes: list = []
    read_camera(str(tmp_path / "c.json"), (1280, 960), notes)
    read_camera(str(tmp_path / "c.json"), (64, 64))
    assert notes == [f"{tmp_path / 'c.json'}: camera key(s) intrinsics.name not used"]
    with pytest.raises(RispError, match=r"a 640×480 camera, but the video's frames are 480×640 pixels"):
        read_camera(str(tmp_path / "c.json"), (480, 640))


def test_camera_field_of_view_is_the_cropped_squares(tmp_path):
    """A 640×480 video is cropped to its centre 480² square: the field of view is that square's."""
    import math

    from risp_tasks.tasks.inputs import read_camera

    (tmp_path / "c.json").write_text(json.dumps({"intrinsics": {"width": 640, "height": 480, "fx": 590.0, "cx": 320},
                                                 "extrinsics": {"origin": [0, -1.7, 2.9], "target": [0, 0, 1.15],
                                                                "up": [0, 0, 1]}}))
    assert read_camera(str(tmp_path / "c.json")).fov == pytest.approx(math.degrees(2 * math.atan(480 / 1180)))


def test_control_refuses_the_options_of_a_video(quad, tmp_path):
    from risp_tasks.video import read_video, write_video

    model, video = quad
    write_video(tmp_path / "goal", read_video(video).frames[-1:], fps=10)
    target = str(tmp_path / "goal" / "frame_00000.png")
    for extra, words in ((["--actions", _actions(video)], "--actions: not used by control"),
                         (["--every", "2"], "--every: not used by control"),
                         (["--source-fps", "30"], "--source-fps: not used by control")):
        line = _invoke(["control", target, "--model", model] + extra, tmp_path)
        assert words in line, line
    line = _invoke(["control", str(tmp_path / "goal"), "--model", model], tmp_path)
    assert "a folder, but control takes one target image" in line


def test_one_frame_is_not_a_motion(quad, tmp_path):
    """sysid and imitate on a single kept frame used to return their start as a result (exit 0)."""
    model, video = quad
    for task in ("sysid", "imitate"):
        line = _invoke([task, video, "--model", model, "--every", "100"], tmp_path)
        assert f"{task} needs at least 2 frames" in line and "got 1 after --every 100" in line, line


def test_video_fps_above_its_own_rate_is_refused(quad, tmp_path):
    model, video = quad
    line = _invoke(["estimate", video, "--model", model, "--fps", "60"], tmp_path)
    assert "--fps 60 is above the video's own 10 frames per second" in line, line


@pytest.mark.parametrize("args,words", [
    (["--params", '{"mass": -3}'], "--params: mass must lie in [1e-09, inf], got -3"),
    (["--effect", "wind:nan,0,0"], "--effect 'wind:nan,0,0': values must be finite numbers"),  # was the renderer's NaN
    (["--resolution", "100000"], "--resolution 100000 is larger than the supported 8192 pixels"),
    (["--spp", "0"], "--spp must be >= 1, got 0"),
])
def test_make_video_checks_physics_and_size_first(tmp_path, args, words):
    """A negative mass used to fly (negative thrusts in the actions file); a huge frame failed in torch."""
    from risp_tasks.cli import cli

    base = ["make-video", "--env", "quadrotor", "--out", str(tmp_path / "v.mp4"), "--frames", "2", "--res", "8",
            "--quiet"]
    line = _error_line(CliRunner().invoke(cli, base + args))
    assert words in line, line
    assert not os.listdir(tmp_path)


def test_a_frame_rate_off_the_hands_fixed_step_lists_the_ones_that_fit():
    from risp_data.errors import RispError
    from risp_tasks.tasks.simulate import timeline

    with pytest.raises(RispError, match=r"30 frames per second do not fit the hand simulator's fixed step of 0.01 s "
                                        r"\(1/fps must be a multiple of it: 100, 50, 33.33, 25, 20, 10, … fps\)"):
        timeline("hand", 30.0)
    assert timeline("quadrotor", 30.0)[1] == 3  # the quadrotor sets its step to 1/90 s instead
    assert timeline("hand", 25.0)[1] == 4
    assert timeline("rod", 100 / 3)[1] == 3 and timeline("hand", 33.3)[1] == 3  # 0.1 % off: fits
    for fps in (7.0, 9.8, 11.0, 14.0, 24.9):  # 0.4-2 % off the nearest fitting rate: the simulated time would drift
        with pytest.raises(RispError, match=f"{fps:g} frames per second do not fit.*with --source-fps"):
            timeline("hand", fps)


@pytest.mark.parametrize("states, problem", [
    ([[1.0, 2.0], [3.0]], "not a table of numbers"),
    ([[0.0] * 3] * 6, "must have 6 columns per row, got shape (6, 3)"),  # the quadrotor's: position, attitude
    ([], "non-empty list of state rows"),
    ([[float("nan")] * 6] * 6, "NaN"),  # json.dumps writes NaN; read_json refuses it or the table check does
])
def test_bad_ground_truth_is_refused_before_any_work(quad, tmp_path, states, problem):
    """A damaged --truth file (ragged rows, another width, empty, NaN) is one line before the optimisation runs,
    for every task that reads one (control reads its last row)."""
    model, video = quad
    path = tmp_path / "truth.json"
    path.write_text(json.dumps({"env": "quadrotor", "env_states": states}))
    for task in ("sysid", "control"):
        args = [task, video, "--model", model, "--truth", str(path)]
        if task == "control":
            from PIL import Image

            Image.new("RGB", (64, 64)).save(tmp_path / "goal.png")
            args[1] = str(tmp_path / "goal.png")
        line = _invoke(args, tmp_path)
        assert "truth.json" in line and problem in line, line


@pytest.mark.parametrize("settings, words", [
    (dict(iterations=-2), "--iterations must be >= 0, got -2"),
    (dict(lr=0.0), "--lr must be a finite number > 0, got 0"),
    (dict(momentum=-0.5), "--momentum must be in [0, 1): RMSProp's momentum; 1 or more diverges, got -0.5"),
    (dict(momentum=float("nan")), "--momentum must be in [0, 1)"),
    (dict(momentum=5.0), "--momentum must be in [0, 1)"),  # accepted, then the loss went NaN at iteration 6
    (dict(fps=0.0), "--fps must be a finite number > 0, got 0"),
    (dict(spp=0), "--spp must be >= 1, got 0"),
    (dict(render_threads=-1), "--render-threads must be >= 0 (0: automatic), got -1"),
    (dict(out=""), "--out is empty"),  # silently wrote to the default folder
    (dict(init="track"), "--init track is imitate's"),
    (dict(task="control", init="track"), "--init track is imitate's"),
    (dict(task="imitate", actions="a.csv"), "--actions: imitate finds the actions itself"),
])
def test_task_settings_name_the_one_bad_option(settings, words):
    """Each bad setting is refused before anything is loaded, by a line that names that option (not a list of
    every rule), including those torch would otherwise refuse with a traceback mid-run (--momentum)."""
    from risp_data.errors import RispError
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RispError) as info:
        TaskConfig(**{"task": "sysid", "video": "v.mp4", **settings})
    assert words in str(info.value) and str(info.value).count("must") <= 1


def test_actions_t_column_must_follow_the_video_timeline(tmp_path):
    """The t column (optional) steps by 1/fps: a file at another rate, or with a row missing, is refused instead of its
    commands being applied at the wrong frames; a t that starts elsewhere (a log's clock), a 29.97 fps log under a
    30 fps video, or clock-time strings (not numbers) are fine."""
    from risp_data.errors import RispError
    from risp_tasks.tasks.inputs import read_actions

    def write(name, times):
        path = tmp_path / name
        path.write_text("t,f0,f1,f2,f3\n" + "".join(f"{t},1,2,3,4\n" for t in times))
        return str(path)

    assert read_actions(write("ok.csv", [0.0, 0.1, 0.2, 0.3]), "quadrotor", 4, 10.0).tolist() == [[1, 2, 3, 4]] * 4
    assert read_actions(write("clock.csv", [12.5, 12.6, 12.7, 12.8]), "quadrotor", 4, 10.0).shape == (4, 4)
    ntsc = [k / 29.97 for k in range(400)]
    assert read_actions(write("ntsc.csv", ntsc), "quadrotor", 400, 30.0).shape == (400, 4)
    assert read_actions(write("hms.csv", ["00:00:00.0", "00:00:00.1"]), "quadrotor", 2, 10.0).shape == (2, 4)
    with pytest.raises(RispError, match=r"slow.csv: t steps from 0 to 0.3 s at line 3 \(3 frames of the video's 10 fps"):
        read_actions(write("slow.csv", [0.0, 0.3, 0.6, 0.9]), "quadrotor", 4, 10.0)
    with pytest.raises(RispError, match=r"gap.csv: t steps from 0.1 to 0.3 s at line 4"):
        read_actions(write("gap.csv", [0.0, 0.1, 0.3, 0.4]), "quadrotor", 4, 10.0)
    with pytest.raises(RispError, match=r"rate.csv: t advances at 11 rows per second, the video at 10 frames"):
        read_actions(write("rate.csv", [k / 11 for k in range(40)]), "quadrotor", 40, 10.0)
    no_t = tmp_path / "no_t.csv"
    no_t.write_text("f0,f1,f2,f3\n" + "1,2,3,4\n" * 4)
    assert read_actions(str(no_t), "quadrotor", 4, 10.0).shape == (4, 4)
    # a t of NaNs skipped the check (exit 0); a column named twice used the first without a word
    with pytest.raises(RispError, match=r"nan_t.csv: column t has NaN/inf at line 2"):
        read_actions(write("nan_t.csv", ["nan", "nan", "nan", "nan"]), "quadrotor", 4, 10.0)
    dup = tmp_path / "dup.csv"
    dup.write_text("t,f0,f1,f2,f3,f0\n" + "".join(f"{k / 10},1,2,3,4,9\n" for k in range(4)))
    with pytest.raises(RispError, match=r"dup.csv: column f0 appears 2 times in the header"):
        read_actions(str(dup), "quadrotor", 4, 10.0)
    blank = tmp_path / "blank.csv"
    blank.write_text("t,f0,f1,f2,f3,,\n" + "".join(f"{k / 10},1,2,3,4,,\n" for k in range(4)))
    with pytest.raises(RispError, match=r"blank.csv: header column 6 has no name \(a trailing comma\?\)"):
        read_actions(str(blank), "quadrotor", 4, 10.0)


def test_a_primal_spp_below_one_is_one_line(quad, tmp_path):
    """--primal-spp (docs/tasks.md §Primal spp) 0 or negative: one line naming the option, no result folder."""
    for value in ("0", "-3"):
        line = _invoke(["sysid", quad[1], "--model", quad[0], "--loss", "render", "--primal-spp", value], tmp_path)
        assert "--primal-spp must be >= 1" in line and value in line, line


HUGE = 10 ** 400  # a JSON integer literal beyond float's range: float() raises OverflowError, not ValueError


@pytest.mark.parametrize("option", ["--spp", "--primal-spp"])
def test_a_sample_count_beyond_mitsubas_limit_is_one_line_before_any_work(quad, tmp_path, monkeypatch, option):
    """Mitsuba counts one render's samples in a uint32: 2^24 spp × 16×16 pixels (the model's) is 2^32, refused
    before the video is read (it failed inside Mitsuba, after the reading and the network's pass)."""
    import risp_tasks.tasks.run as run_mod

    monkeypatch.setattr(run_mod, "_reference", lambda *a, **k: pytest.fail("read the video before checking"))
    line = _invoke(["sysid", quad[1], "--model", quad[0], "--loss", "render", option, str(2**24)], tmp_path)
    assert f"{option} 16777216 needs 4,294,967,296 samples per rendered frame (16×16 pixels" in line, line
    assert "limit of 2^32" in line


@pytest.mark.parametrize("params", ["3.0", None, [3.0], {"mass": HUGE}, {"mass": True}])
def test_truth_with_bad_params_is_refused_before_any_work(quad, tmp_path, params):
    """The truth's hidden parameters are what the errors are measured against: a string, null, a list or an
    out-of-range number used to raise a TypeError after the whole optimisation (or drop the errors silently)."""
    model, video = quad
    truth = json.load(open(os.path.splitext(video)[0] + ".truth.json"))
    truth["params"] = params if not isinstance(params, str) else {"mass": params}
    path = tmp_path / "truth.json"
    path.write_text(json.dumps(truth))
    line = _invoke(["sysid", video, "--model", model, "--actions", _actions(video), "--truth", str(path)], tmp_path)
    assert "truth.json" in line and "'params' must be an object of finite numbers" in line, line


def test_integers_beyond_float_are_one_line(quad, tmp_path):
    """Huge integer literals in the truth, camera and initial-state JSON: one line each, not an OverflowError."""
    model, video = quad
    truth = json.load(open(os.path.splitext(video)[0] + ".truth.json"))
    truth["env_states"][0][0] = HUGE
    (tmp_path / "truth.json").write_text(json.dumps(truth))
    line = _invoke(["sysid", video, "--model", model, "--actions", _actions(video), "--truth",
                    str(tmp_path / "truth.json")], tmp_path)
    assert "truth.json" in line and "not a table of numbers" in line, line
    camera = {"intrinsics": {"width": 64, "height": 64, "fx": HUGE},
              "extrinsics": {"origin": [0, -2, 2], "target": [0, 0, 1], "up": [0, 0, 1]}}
    (tmp_path / "camera.json").write_text(json.dumps(camera))
    line = _invoke(["sysid", video, "--model", model, "--actions", _actions(video), "--loss", "render",
                    "--camera", str(tmp_path / "camera.json")], tmp_path)
    assert "camera.json" in line and "camera values must be numbers" in line, line
    from PIL import Image

    Image.new("RGB", (64, 64)).save(tmp_path / "goal.png")
    (tmp_path / "s0.json").write_text(json.dumps({"env_state": [HUGE, 0, 1, 0, 0, 0]}))
    line = _invoke(["control", str(tmp_path / "goal.png"), "--model", model, "--initial-state",
                    str(tmp_path / "s0.json")], tmp_path)
    assert "s0.json" in line and "must be a list of numbers" in line, line


def test_an_actions_csv_the_csv_module_cannot_parse_is_one_line(quad, tmp_path):
    model, video = quad
    rows = open(_actions(video)).read().splitlines()
    rows[2] += "x" * 200_000  # one field over the csv module's 128 KiB limit (an unclosed quote in a large file)
    (tmp_path / "long.csv").write_text("\n".join(rows) + "\n")
    line = _invoke(["sysid", video, "--model", model, "--actions", str(tmp_path / "long.csv")], tmp_path)
    assert "long.csv" in line and "not a readable actions CSV" in line and "field limit" in line, line


def test_the_frame_count_of_an_actions_mismatch_names_the_fps(quad, tmp_path):
    """With --fps the timeline is the resampled one: '6 rows but 3 frames' alone read as if the video had 3."""
    model, video = quad
    line = _invoke(["sysid", video, "--model", model, "--actions", _actions(video), "--fps", "5"], tmp_path)
    assert "6 action rows but the video has 3 frames at --fps 5" in line, line


def test_rod_forces_the_simulator_would_clip_are_refused():
    """The rod's centre force is clamped at ±500 N: a file in other units (mN) was clipped without a word."""
    from risp_data.errors import RispError
    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.run import _check_action_range

    rod = get_simulator("rod")
    _check_action_range("ok.csv", rod, np.array([[-500.0], [499.0]]))  # the clamp's range is fine
    with pytest.raises(RispError, match=r"big.csv: centre forces up to 2e\+04 N, above the 500 N the simulated rod"):
        _check_action_range("big.csv", rod, np.array([[20000.0], [3.0]]))


def test_params_out_of_physical_bounds_name_the_option():
    from risp_data.errors import RispError
    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.simulate import read_params

    quad = get_simulator("quadrotor")
    assert read_params(quad, '{"mass": 3.1}') == {"mass": 3.1}
    for given, words in (('{"mass": -3}', "--params: mass must lie in [1e-09, inf], got -3"),
                         ('{"k_f": 0}', "--params: k_f must lie in")):
        with pytest.raises(RispError, match=words.replace("[", r"\[").replace("]", r"\]")):
            read_params(quad, given)


def test_check_param_bounds_refuses_nan():
    import torch

    from risp_data.errors import RispError
    from risp_tasks.sims import get_simulator

    quad = get_simulator("quadrotor")
    p = quad.default_params()
    p[0, 0] = float("nan")
    with pytest.raises(RispError, match="must lie in"):
        quad.check_param_bounds(p)
    quad.check_param_bounds(quad.default_params())
    assert torch.isfinite(quad.default_params()).all()


def test_out_under_a_file_is_refused_before_any_work(quad, tmp_path):
    """--out v.mp4/res used to fail after the optimisation, with the operating system's 'File exists'."""
    model, video = quad
    from risp_tasks.cli import cli

    (tmp_path / "a.txt").write_text("a file")
    res = CliRunner().invoke(cli, ["sysid", video, "--model", model, "--actions", _actions(video), "--out",
                                   str(tmp_path / "a.txt" / "res"), "--quiet", "--iterations", "1", "--no-plots"])
    line = _error_line(res, skip="model: ")
    assert "a.txt is a file, not a folder" in line, line


def test_a_start_that_simulates_to_nan_points_at_the_inputs(quad, tmp_path, monkeypatch):
    """A loss that is NaN before any step: the inputs diverge; --lr (the old advice) cannot help."""
    import risp_tasks.tasks.run as run_mod

    real = run_mod.make_loss

    def nan_loss(*args, **kwargs):
        loss = real(*args, **kwargs)
        return lambda s, n=None: (loss(s) if n is None else loss(s, n)) * float("nan")

    monkeypatch.setattr(run_mod, "make_loss", nan_loss)
    model, video = quad
    line = _invoke(["sysid", video, "--model", model, "--actions", _actions(video)], tmp_path)
    assert "NaN/inf at the start, before any optimisation step" in line and "--actions" in line, line


def test_a_still_image_as_the_video_needs_its_frame_rate(quad, tmp_path):
    """One PNG given as the video: FFmpeg's image demuxer reports a made-up 25 fps, which result.json recorded as
    the video's rate; like a PNG folder, a still picture has none until --source-fps gives it."""
    model, video = quad
    from PIL import Image

    Image.new("RGB", (64, 64), (90, 120, 150)).save(tmp_path / "still.png")
    line = _invoke(["estimate", str(tmp_path / "still.png"), "--model", model], tmp_path)
    assert "still.png" in line and "frame rate is unknown" in line and "--source-fps" in line, line
    from risp_tasks.cli import cli

    res = CliRunner().invoke(cli, ["estimate", str(tmp_path / "still.png"), "--model", model, "--source-fps", "10",
                                   "--out", str(tmp_path / "est"), "--quiet", "--no-plots"])
    assert res.exit_code == 0, res.output
    assert json.load(open(tmp_path / "est" / "result.json"))["video"]["fps"] == 10


def test_folders_given_for_files_and_output_folders_given_as_videos(quad, tmp_path):
    """A folder where a truth/actions file goes says so (it said 'file not found'); a risp output folder given as
    the video is named for what it is (a run folder's loss plot was read as a one-frame video with --source-fps)."""
    model, video = quad
    (tmp_path / "emptyd").mkdir()
    line = _invoke(["sysid", video, "--model", model, "--truth", str(tmp_path / "emptyd")], tmp_path)
    assert "emptyd: a folder, not a ground-truth file" in line, line
    line = _invoke(["sysid", video, "--model", model, "--actions", str(tmp_path / "emptyd")], tmp_path)
    assert "emptyd: a folder, not an actions file" in line, line
    run = os.path.dirname(model)
    line = _invoke(["estimate", run, "--model", model, "--source-fps", "10"], tmp_path)
    assert "a risp-train run folder (model.pt), not a video" in line, line


def test_a_linked_out_in_a_folder_that_cannot_be_written_is_refused_before_the_work(quad, tmp_path, monkeypatch):
    """--overwrite onto a link to a result folder: the temporary goes beside the link, so the link's own folder must
    be writable too — checked before the optimisation, not found out after it."""
    import risp_tasks.tasks.run as run_mod
    from risp_tasks.cli import cli

    real = tmp_path / "disk" / "res"
    real.mkdir(parents=True)
    (real / "result.json").write_text("{}")
    locked = tmp_path / "locked"
    locked.mkdir()
    os.symlink(real, locked / "res")
    _deny_writes_in(monkeypatch, locked)
    monkeypatch.setattr(run_mod, "optimize", lambda *a, **k: pytest.fail("optimised before checking --out"))
    res = CliRunner().invoke(cli, ["estimate", quad[1], "--model", quad[0], "--out", str(locked / "res"), "--quiet",
                                   "--overwrite"])
    assert "no write permission" in _error_line(res, skip="model: ")
    assert os.listdir(real) == ["result.json"]
