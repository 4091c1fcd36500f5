"""Acceptance of diagnose on flights it has never seen (issue 12): an independent generator (numpy, RK4 at
1 kHz, its own cascaded PD controller; tests/diagnose_independent.py), never the project's simulator.

* effect-free -> ``none`` with ρ ≤ 1.15;
* wind, linear (rotor) drag, quadratic drag, motor lag, ground effect per rotor and on the total thrust ->
  named right, parameters within 20 %, held-out rollout error (normalised by the noise) −50 % or better;
* a time-varying gust -> never a confident wrong name (``unexplained``);
* the issue's confident wrong name: ground effect on the total thrust offered only a constant force
  -> ``unexplained`` naming the regressor the residual still depends on;
* error bars: |fit − truth| ≤ 3σ for at least 90 % of the fitted parameters over all named cases.

Each case is 4 flights × 3 s at 100 Hz; runs are cached per module so the coverage test reuses them.
"""

from __future__ import annotations

import pytest

from diagnose_independent import write_flights
from risp_tasks.diagnose.run import DiagnoseConfig, diagnose

pytestmark = pytest.mark.slow

CASES = {
    "wind": ({"fx": 4.0, "fy": -2.5, "fz": 1.5}, 5),
    "rotor_drag": ({"dx": 0.6, "dy": 0.5, "dz": 0.25}, 6),
    "air_drag": ({"c": 0.12}, 7),
    "motor_lag": ({"tau": 0.06}, 4),
    "ground_effect": ({"k": 1.2}, 3),
    "ground_effect_centre": ({"k": 1.5}, 2),
}
_RUNS: dict = {}


def run(tmp_path_factory, effect, par, seed, effects=None):
    key = (effect, seed, effects)
    if key not in _RUNS:
        folder = write_flights(tmp_path_factory.mktemp(f"flights_{effect}"), effect, par, seed=seed)
        _RUNS[key] = diagnose(DiagnoseConfig(data=(str(folder),), env="quadrotor", out=None, seed=seed, pairs_top=2,
                                             progress=False, plots=False, effects=effects))
    return _RUNS[key]


def test_effect_free_is_none_at_the_noise_floor(tmp_path_factory):
    rep = run(tmp_path_factory, None, {}, 1)
    assert rep["cause"] == "none", rep["reason"]
    assert rep["base_error"]["noise_floor_ratio"] <= 1.15


@pytest.mark.parametrize("effect", list(CASES))
def test_hidden_effect_named_recovered_and_improves_rollout(tmp_path_factory, effect):
    par, seed = CASES[effect]
    rep = run(tmp_path_factory, effect, par, seed)
    assert rep["cause"] == effect, (rep["reason"], rep["ranking"][:3])
    for p, truth in par.items():
        got = rep["parameters"][f"{effect}.{p}"]
        assert abs(got["value"] - truth) <= 0.2 * abs(truth), (p, truth, got)
        assert "at_bound" not in got
    assert rep["gain"]["rollout_normalized"] >= 0.5, rep["gain"]


def test_gust_is_never_a_confident_wrong_name(tmp_path_factory):
    rep = run(tmp_path_factory, "gust", {"amplitude": 0.2, "phase": 0.4}, 8)
    assert rep["cause"] == "unexplained", rep["reason"]


def test_constant_force_on_a_height_dependent_residual_is_not_named(tmp_path_factory):
    """Issue 12 §1: ground effect on the total thrust, only a constant force on offer."""
    rep = run(tmp_path_factory, "ground_effect_centre", {"k": 1.5}, 2, effects=("wind",))
    assert rep["cause"] == "unexplained", rep["reason"]
    assert "still depends on" in rep["reason"]
    assert any(d["significant"] for d in rep["residual_dependence"])


def test_error_bars_cover_the_truth(tmp_path_factory):
    within, total = 0, 0
    for effect, (par, seed) in CASES.items():
        rep = run(tmp_path_factory, effect, par, seed)
        for p, truth in par.items():
            got = rep["candidate_parameters"][effect][f"{effect}.{p}"]
            total += 1
            within += abs(got["value"] - truth) <= 3 * got["std"]
    assert within >= 0.9 * total, (within, total)


def test_px4_style_log_fits_a_known_wind(tmp_path):
    """X frame with PX4 motor numbering, 0.16 m arms, scalar-last quaternion, world-frame rates, PWM with a
    hover throttle: read as declared in the sidecar, the thrust map k_f is fitted and the wind recovered."""
    from diagnose_independent import PX4_FULL_THRUST, write_px4_flights

    wind = (6.0, -3.0, 1.0)
    folder = write_px4_flights(tmp_path / "px4", wind, seed=9)
    rep = diagnose(DiagnoseConfig(data=(str(folder),), env="quadrotor", out=None, seed=9, pairs_top=2,
                                  progress=False, plots=False, effects=("wind", "air_drag", "motor_lag")))
    assert rep["cause"] == "wind", rep["reason"]
    for name, truth in zip(("fx", "fy", "fz"), wind):
        got = rep["parameters"][f"wind.{name}"]
        assert abs(got["value"] - truth) <= 0.2 * abs(truth), (name, got)
    assert rep["parameters"]["k_f"]["value"] == pytest.approx(PX4_FULL_THRUST, rel=0.05)


def test_filtered_noise_is_flagged_and_declared_noise_is_used(tmp_path):
    """Issue 12 §noise: time-correlated (AR(1), φ = 0.8) measurement noise on effect-free flights.  The
    estimate flags it (and never names a cause from it); a sidecar that declares the sensor noise and its
    correlation is used as given, the bootstrap draws AR(1) noise, and the base sits at the noise floor."""
    from diagnose_independent import NOISE, SIDECAR

    folder = write_flights(tmp_path / "filtered", None, {}, seed=11, phi=0.8)
    rep = diagnose(DiagnoseConfig(data=(str(folder),), env="quadrotor", out=None, seed=1, pairs_top=2,
                                  progress=False, plots=False, effects=("wind", "air_drag")))
    assert rep["noise_model"]["time_correlated"] and rep["noise_model"]["source"].startswith("estimated")
    assert rep["cause"] in ("none", "unexplained"), rep["reason"]
    declared = {**SIDECAR, "measurement_noise": NOISE, "measurement_noise_correlation": 0.8}
    folder = write_flights(tmp_path / "declared", None, {}, seed=11, phi=0.8, sidecar=declared)
    rep = diagnose(DiagnoseConfig(data=(str(folder),), env="quadrotor", out=None, seed=1, pairs_top=2,
                                  progress=False, plots=False, effects=("wind", "air_drag")))
    assert rep["noise_model"]["source"] == "declared in the sidecar"
    assert rep["noise"] == NOISE and rep["noise_model"]["lag1_correlation"]["velocity"] == 0.8
    assert rep["cause"] == "none" and rep["base_error"]["noise_floor_ratio"] <= 1.3, rep["reason"]


def test_collective_throttle_log_in_translational_mode(tmp_path):
    """A log with only a normalised collective throttle (and the attitude): the translational model
    (attitude from the data) fits the thrust map (4·12 N per unit throttle) and the wind."""
    from diagnose_independent import PX4_FULL_THRUST, write_px4_flights

    wind = (6.0, -3.0, 1.0)
    folder = write_px4_flights(tmp_path / "px4c", wind, seed=9, collective=True)
    rep = diagnose(DiagnoseConfig(data=(str(folder),), env="quadrotor", out=str(tmp_path / "rep"), seed=9,
                                  pairs_top=2, progress=False, plots=True, effects=("wind", "air_drag", "motor_lag")))
    assert rep["cause"] == "wind", rep["reason"]
    for name, truth in zip(("fx", "fy", "fz"), wind):
        assert abs(rep["parameters"][f"wind.{name}"]["value"] - truth) <= 0.2 * abs(truth), rep["parameters"]
    assert rep["parameters"]["k_f"]["value"] == pytest.approx(4 * PX4_FULL_THRUST, rel=0.05)
    assert set(rep["noise"]) == {"coordinate", "rate"}  # position and velocity channels only


def test_quadratic_thrust_map_is_fitted(tmp_path):
    """PWM whose thrust map is f = 7·u + 6·u² (sidecar "thrust_map": "quadratic"): both coefficients and the
    wind are recovered."""
    from diagnose_independent import write_px4_flights

    wind = (6.0, -3.0, 1.0)
    folder = write_px4_flights(tmp_path / "px4q", wind, seed=9, quadratic=(7.0, 6.0))
    rep = diagnose(DiagnoseConfig(data=(str(folder),), env="quadrotor", out=None, seed=9, pairs_top=0,
                                  progress=False, plots=False, effects=("wind", "air_drag")))
    assert rep["cause"] == "wind", rep["reason"]
    assert rep["parameters"]["k_f"]["value"] == pytest.approx(7.0, rel=0.1), rep["parameters"]
    assert rep["parameters"]["k_f2"]["value"] == pytest.approx(6.0, rel=0.1), rep["parameters"]
    assert abs(rep["parameters"]["wind.fx"]["value"] - 6.0) <= 1.2
