"""risp-task diagnose on synthetic quadrotor flights with a hidden effect (issue 4 acceptance)."""

from __future__ import annotations

import json

import pytest

from diagnose_helpers import assert_recovered, run_case
from risp_tasks.diagnose.candidates import effect_names

QUAD_EFFECTS = ("rotor_drag", "air_drag", "wind", "motor_lag", "ground_effect", "ground_effect_centre")


def test_library_is_the_simulators():
    assert set(effect_names("quadrotor")) == set(QUAD_EFFECTS)


@pytest.mark.parametrize("seed, effect", [(11, "rotor_drag"), (12, "air_drag"), (13, "wind"), (14, "motor_lag"),
                                          (15, "ground_effect")])
def test_hidden_effect_is_named_and_recovered(tmp_path, seed, effect):
    truth, report = run_case(tmp_path, "quadrotor", effect, seed, out=False)
    assert_recovered("quadrotor", truth, report)
    assert report["gain"]["normalized_rss"] > 0.05


def test_random_effect_with_report_files(tmp_path):
    truth, report = run_case(tmp_path, "quadrotor", "random", seed=21)
    assert_recovered("quadrotor", truth, report)
    out = tmp_path / "report"
    saved = json.loads((out / "report.json").read_text())
    for key in ("cause", "parameters", "ranking", "base_error", "extended_error", "gain", "split", "seed"):
        assert key in saved
    assert saved["split"]["mode"] == "trajectories" and saved["seed"] == 21
    assert set(saved["split"]["fit"]).isdisjoint(saved["split"]["held_out"])
    md = (out / "report.md").read_text()
    assert f"Cause: `{truth['effect']}`" in md
    for png in ("residuals_over_time.png", "residuals_vs_regressors.png", "gain_overlay.png", "ranking.png"):
        assert (out / png).stat().st_size > 5000
    # the extended model is better on held-out data in every reported measure of velocity error
    assert saved["extended_error"]["rollout"]["velocity"] < saved["base_error"]["rollout"]["velocity"]


def test_null_case_is_none(tmp_path):
    truth, report = run_case(tmp_path, "quadrotor", None, seed=31, out=False)
    assert truth["effect"] is None
    assert report["cause"] == "none", report["reason"]
    assert report["parameters"] == {}


def test_unlisted_effect_is_unexplained(tmp_path):
    truth, report = run_case(tmp_path, "quadrotor", "periodic_force", seed=41, out=False)
    assert report["cause"] == "unexplained", report["reason"]


def test_cli_end_to_end(tmp_path):
    from click.testing import CliRunner

    from risp_tasks.cli import cli
    from risp_tasks.diagnose.synth import SynthConfig, make_synthetic

    make_synthetic(SynthConfig(env="quadrotor", seed=71, n_traj=3, samples=150, effect="wind"), tmp_path / "d")
    out = tmp_path / "rep"
    res = CliRunner().invoke(cli, ["diagnose", str(tmp_path / "d"), "--env", "quadrotor", "--out", str(out),
                                   "--seed", "4", "--effects", "wind,air_drag", "--quiet", "--no-plots"])
    assert res.exit_code == 0, res.output
    assert res.output.startswith("cause: wind")
    saved = json.loads((out / "report.json").read_text())
    assert saved["config"]["effects"] == ["wind", "air_drag"] and saved["seed"] == 4
    bad = CliRunner().invoke(cli, ["diagnose", str(tmp_path / "d"), "--env", "quadrotor", "--out", str(out),
                                   "--effects", "wind,tornado", "--quiet"])
    assert bad.exit_code != 0 and "unknown effect(s) tornado" in bad.output
