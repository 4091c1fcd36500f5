"""The users' two commands, verbatim (tiny --n): `risp-data render --env cube --n N` then `risp-train fit shards/`
(issue 8, item 7): default output under shards/, a folder of data sets accepted, default run folder under
runs/, the hardware's preset and RISP's regularizer, both printed."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from risp_data.errors import RispError
from risp_train.cli import find_dataset


def _run(args, cwd):
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                           os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=900)


@pytest.mark.slow
def test_render_then_fit_work_as_users_write_them(tmp_path):
    r = _run(["risp_data", "render", "--env", "cube", "--n", "32", "--quiet"], tmp_path)
    assert r.returncode == 0, r.stderr
    manifest = json.load(open(tmp_path / "shards" / "cube-train" / "manifest.json"))
    assert manifest["env"] == "cube" and manifest["counts"]["complete_samples"] == 32 and manifest["jacobian"]
    r = _run(["risp_train", "fit", "shards/", "--quiet"], tmp_path)
    assert r.returncode == 0, r.stderr
    run = tmp_path / "runs" / "cube-train-stochastic-s0"
    assert (run / "model.pt").exists()
    cfg = json.load(open(run / "config.json"))["config"]
    import torch

    expected = "paper" if torch.cuda.is_available() else "cpu"
    assert cfg["preset"] == expected and cfg["reg"] == "stochastic"
    assert f"preset: {expected}" in r.stderr and "regularizer: stochastic" in r.stderr
    # the schedule is said as resolved for the cube: its γ starts at half the run (GAMMA_START_DEFAULTS)
    assert "γ 0.3 from 50% of the steps, ramped in over 50% of the rest" in r.stderr
    assert cfg["gamma_start"] is None and json.load(open(run / "config.json"))["gamma_start"] == 0.5
    # a closing line with the last epoch's figures, read from the run's history
    last = json.load(open(run / "history.json"))[-1]
    assert f"epoch {last['epoch'] + 1}: training error {last['train_error']:.4g}" in r.stderr, r.stderr


def test_fit_closes_with_the_last_epochs_errors(tmp_path):
    """The closing line: training error, regularizer and validation error of the last epoch; none when the history
    cannot be read."""
    from risp_train.cli import last_epoch_summary

    (tmp_path / "history.json").write_text(json.dumps([
        {"epoch": 0, "train_error": 0.9, "train_reg": 0.2},
        {"epoch": 1, "train_error": 0.31219, "train_loss": 0.33, "train_reg": 0.054, "val_error": 0.5456}]))
    line = last_epoch_summary(str(tmp_path))
    assert line.startswith("epoch 2: training error 0.3122; regularizer 0.054; validation error 0.5456 (L1 on ")
    (tmp_path / "history.json").write_text("[]")
    assert last_epoch_summary(str(tmp_path)) is None and last_epoch_summary(str(tmp_path / "nosuch")) is None


def _dataset(folder, domain="train", jacobian=True, env="cube"):
    os.makedirs(folder)
    with open(os.path.join(folder, "manifest.json"), "w") as f:
        json.dump({"env": env, "domain": domain, "jacobian": jacobian, "n": 4}, f)
    return str(folder)


def test_find_dataset_picks_the_one_training_set_or_lists_them(tmp_path):
    one = _dataset(tmp_path / "a" / "cube-train")
    assert find_dataset(str(tmp_path / "a"), need_jacobian=True) == one
    assert find_dataset(one, need_jacobian=True) == one
    _dataset(tmp_path / "a" / "cube-target", domain="target", jacobian=False)
    assert find_dataset(str(tmp_path / "a"), need_jacobian=True) == one  # the one train-domain set
    _dataset(tmp_path / "a" / "quadrotor-train", env="quadrotor")
    with pytest.raises(RispError, match="holds 3 data sets: .*cube-target.*cube-train.*quadrotor-train"):
        find_dataset(str(tmp_path / "a"), need_jacobian=True)
    os.makedirs(tmp_path / "empty")
    with pytest.raises(RispError, match="holds no data set"):
        find_dataset(str(tmp_path / "empty"), need_jacobian=False)
    with pytest.raises(RispError, match="does not exist"):
        find_dataset(str(tmp_path / "missing"), need_jacobian=False)


def test_find_dataset_skips_a_manifest_that_is_not_a_json_object(tmp_path):
    one = _dataset(tmp_path / "a" / "cube-train")
    _dataset(tmp_path / "a" / "cube-target", domain="target", jacobian=False)
    os.makedirs(tmp_path / "a" / "odd")
    (tmp_path / "a" / "odd" / "manifest.json").write_text("[]")  # valid JSON, not a manifest
    assert find_dataset(str(tmp_path / "a"), need_jacobian=True) == one


def test_eval_with_a_negative_seed_or_batch_is_one_error_line(tmp_path):
    from click.testing import CliRunner

    from risp_train.cli import cli

    for args, words in ((["--seed", "-1"], "--seed must be >= 0"), (["--batch-size", "0"], "--batch-size >= 1")):
        res = CliRunner().invoke(cli, ["eval", str(tmp_path / "model.pt"), str(tmp_path / "shards"), *args])
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert res.exit_code != 0 and len(lines) == 1 and lines[0].startswith("Error: ") and words in lines[0], res.output


def test_help_does_not_import_torch_or_mitsuba():
    """`risp-task --help`, `risp-train --help`, `risp --help` took 1.3–2 s, nearly all of it importing torch for the
    --env choices and the default regularizer; the command modules now import neither torch nor Mitsuba (nor numpy:
    the option choices are literals)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = ("import sys, cli, risp_data.cli, risp_train.cli, risp_tasks.cli, risp_tasks.demo\n"
            "from click.testing import CliRunner\n"
            "out = CliRunner().invoke(cli.cli, ['--help']).output\n"
            "assert all(name in out for name in ('data', 'train', 'task', 'demo')), out\n"
            "print(sorted(m for m in ('torch', 'mitsuba', 'drjit', 'numpy') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout
    from risp_data.envs import Camera, Environment, Mesh  # the lazy names still resolve

    assert Camera.__name__ == "Camera" and Environment.__name__ == "Environment" and Mesh.__name__ == "Mesh"


def test_find_dataset_names_a_damaged_manifest_instead_of_passing_it_over(tmp_path):
    """A truncated manifest.json beside a target set: the folder counted as holding the target set alone, and fit
    trained on that; a file given as the folder was 'does not exist'."""
    _dataset(tmp_path / "a" / "cube-target", domain="target", jacobian=False)
    os.makedirs(tmp_path / "a" / "cube-train")
    (tmp_path / "a" / "cube-train" / "manifest.json").write_text('{"env": "cube", "dom')
    with pytest.raises(RispError, match=r"unreadable manifest .*cube-train/manifest.json \(JSONDecodeError\)"):
        find_dataset(str(tmp_path / "a"), need_jacobian=False)
    (tmp_path / "f").write_text("x")
    with pytest.raises(RispError, match="is a file, not a shard folder"):
        find_dataset(str(tmp_path / "f"), need_jacobian=False)
