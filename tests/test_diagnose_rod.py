"""risp-task diagnose on a synthetic rod (FEM, reverse-mode derivatives only: L-BFGS-B fallback)."""

from __future__ import annotations

from diagnose_helpers import assert_recovered
from risp_tasks.diagnose.run import DiagnoseConfig, diagnose
from risp_tasks.diagnose.synth import SynthConfig, make_synthetic


def _run(tmp_path, effect, seed):
    truth = make_synthetic(SynthConfig(env="rod", seed=seed, n_traj=3, samples=60, effect=effect), tmp_path / "data")
    report = diagnose(DiagnoseConfig(data=(str(tmp_path / "data"),), env="rod", out=None, seed=seed, horizon=5,
                                     progress=False, plots=False))
    return truth, report


def test_hidden_rayleigh_damping_is_named_and_recovered(tmp_path):
    truth, report = _run(tmp_path, "rayleigh_damping", seed=61)
    assert_recovered("rod", truth, report)


def test_null_case_is_none(tmp_path):
    _, report = _run(tmp_path, None, seed=62)
    assert report["cause"] == "none", report["reason"]
