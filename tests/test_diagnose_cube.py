"""risp-task diagnose on synthetic cube tosses (148 Hz, the real cube's size and mass) and on real tosses.

Restitution is not among the hidden-effect cases: with 4 tosses × 120 samples its effect on the few impact
segments is below the detection threshold (diagnose answers ``none``, not a wrong name; docs/diagnose.md).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from diagnose_helpers import assert_recovered, run_case
from risp_tasks.diagnose.run import DiagnoseConfig, diagnose

# The project's shared data beside the checkout (CI), else the 12 tosses bundled with the package.
CUBE_TOSSES = Path(__file__).resolve().parents[2] / "shared" / "data" / "cube-tosses"
if not CUBE_TOSSES.is_dir():
    CUBE_TOSSES = Path(__file__).resolve().parents[1] / "risp_tasks" / "data" / "cube_tosses"


@pytest.mark.slow
@pytest.mark.parametrize("seed, effect", [(81, "friction"), (82, "rolling_friction")])
def test_hidden_effect_is_named_and_recovered(tmp_path, seed, effect):
    truth, report = run_case(tmp_path, "cube", effect, seed, samples=100, pairs_top=0, out=False, max_iters=12)
    assert_recovered("cube", truth, report)


@pytest.mark.slow
def test_unlisted_periodic_force_is_unexplained(tmp_path):
    _, report = run_case(tmp_path, "cube", "periodic_force", seed=84, n_traj=3, samples=100, pairs_top=0, out=False,
                         max_iters=6)
    assert report["cause"] == "unexplained", report["reason"]


@pytest.mark.skipif(not CUBE_TOSSES.is_dir(), reason="real cube tosses not available")
def test_real_tosses_small_run(tmp_path):
    """Four real tosses, one held out, friction only: a report with a floor calibration and a gain."""
    report = diagnose(DiagnoseConfig(data=(str(CUBE_TOSSES),), env="cube", out=str(tmp_path / "r"), seed=0,
                                     limit=4, held_out=0.25, effects=("friction",), pairs_top=0,
                                     max_iters=6, progress=False, plots=True))
    floor = report["data"]["floor_calibration"]
    assert floor["applied"] and -0.005 < floor["floor_offset_m"] < 0.0
    # estimated on the fitting part's resting frames only: the same offset as the three fitting tosses alone give
    from risp_tasks.diagnose.adapter import calibrate_floor
    from risp_tasks.measured import load_measured

    fit = [t for t in load_measured([str(CUBE_TOSSES)], "cube", limit=4) if t.name in report["split"]["fit"]]
    assert len(fit) == 3 and calibrate_floor(fit)[1] == floor
    # fitted base parameters carry their units (log10_kn, dn were printed bare)
    units = {n: p["unit"] for ps in report["candidate_parameters"].values() for n, p in ps.items()}
    assert units.get("dn") == "N s/m" and units.get("log10_kn") == "log10(N/m)", units
    assert report["split"]["mode"] == "trajectories" and len(report["split"]["held_out"]) == 1
    assert report["cause"] != "none"  # a frictionless cube cannot explain real tosses
    friction = next(r for r in report["ranking"] if r["model"] == "friction")
    assert friction["delta_bic"] > 10 and friction["rss_reduction"] > 0.05
    assert (tmp_path / "r" / "gain_overlay.png").is_file()
