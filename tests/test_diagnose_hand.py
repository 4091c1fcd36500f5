"""risp-task diagnose on synthetic hand motions with a hidden effect (issue 4 acceptance, hand)."""

from __future__ import annotations

import pytest

from diagnose_helpers import assert_recovered, run_case


@pytest.mark.parametrize("seed, effect", [(51, "joint_damping"), (52, "joint_friction"), (53, "gravity")])
def test_hidden_effect_is_named_and_recovered(tmp_path, seed, effect):
    truth, report = run_case(tmp_path, "hand", effect, seed, samples=150, out=False)
    assert_recovered("hand", truth, report)


def test_null_case_is_none(tmp_path):
    _, report = run_case(tmp_path, "hand", None, seed=54, samples=150, out=False)
    assert report["cause"] == "none", report["reason"]
    # the hand's generalised coordinates are joint angles: report.md's units say so (they were blank or m/s²-less)
    from risp_tasks.diagnose.report import markdown

    md = markdown(report)
    assert "| coordinate [rad] |" in md and "| rate [rad/s] |" in md and "| rate derivative [rad/s²] |" in md, md
    assert "coordinate []" not in md


def test_units_of_the_generalised_coordinates():
    from risp_tasks.diagnose.residuals import unit_of

    assert [unit_of(g, "rod") for g in ("coordinate", "rate", "rate derivative")] == ["m", "m/s", "m/s²"]
    assert [unit_of(g, "quadrotor") for g in ("coordinate", "rate", "acceleration")] == ["m", "m/s", "m/s²"]
    assert unit_of("angular acceleration") == "rad/s²" and unit_of("position") == "m"


def test_wrong_fixed_stiffness_is_unexplained(tmp_path):
    """A base parameter that diagnose keeps fixed is wrong: no library effect may take the blame."""
    _, report = run_case(tmp_path, "hand", "stiffness_error", seed=55, samples=150, out=False)
    assert report["cause"] == "unexplained", report["reason"]
