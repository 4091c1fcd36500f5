"""The diagnose machinery: exact Jacobians, noise estimation, split, decision rule."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from risp_tasks.diagnose import candidates as cands
from risp_tasks.diagnose.adapter import Observer
from risp_tasks.diagnose.fit import _jacobian, channel_sigma, estimate_noise, grid_start, make_segments, residuals
from risp_tasks.diagnose.run import split_trajectories
from risp_data.errors import RispError
from risp_tasks.diagnose.select import Score, decide, estimate_force_note, estimate_note
from risp_tasks.diagnose.synth import SynthConfig, make_synthetic
from risp_tasks.measured import load_measured


@pytest.fixture(scope="module")
def quad_data(tmp_path_factory):
    d = tmp_path_factory.mktemp("quad")
    truth = make_synthetic(SynthConfig(env="quadrotor", seed=5, n_traj=3, samples=120, effect="motor_lag"), d)
    return d, truth


def test_forward_mode_jacobian_matches_central_differences(quad_data):
    """∂e/∂z of the multiple-shooting residuals (float64) vs central finite differences."""
    d, _ = quad_data
    trajs = load_measured([str(d)], "quadrotor")
    model, k = cands.build_model("quadrotor", ("motor_lag", "air_drag"), trajs[0].sidecar, trajs[0].dt)
    obs = Observer(model.sim)
    noise = estimate_noise(model.sim, trajs)
    seg = make_segments(model.sim, trajs, horizon=5, k=k, params=model.base)
    sigma = channel_sigma(obs, noise)
    fn = lambda z: residuals(model.sim, obs, model.params(z), seg, sigma).reshape(-1)  # noqa: E731
    z = torch.tensor([0.3, -0.2], dtype=torch.float64)
    J = _jacobian(fn, z)
    eps = 1e-6
    for j in range(2):
        dz = torch.zeros(2, dtype=torch.float64)
        dz[j] = eps
        with torch.no_grad():
            fd = (fn(z + dz) - fn(z - dz)) / (2 * eps)
        assert torch.allclose(J[:, j], fd, rtol=1e-4, atol=1e-6 * fd.abs().max())


def test_noise_estimate_recovers_the_synthetic_level(quad_data):
    d, truth = quad_data
    trajs = load_measured([str(d)], "quadrotor")
    model, _ = cands.build_model("quadrotor", (), trajs[0].sidecar, trajs[0].dt)
    est = estimate_noise(model.sim, trajs)
    for g, true in truth["noise"].items():
        assert est[g] == pytest.approx(true, rel=0.2), g


def test_split_by_trajectories_is_seeded_and_by_time_for_one_file(quad_data):
    d, _ = quad_data
    trajs = load_measured([str(d)], "quadrotor")
    a = split_trajectories(trajs, 0.3, seed=3)[2]
    b = split_trajectories(trajs, 0.3, seed=3)[2]
    assert a == b and a["mode"] == "trajectories" and len(a["held_out"]) == 1 and len(a["fit"]) == 2
    fit, held, info = split_trajectories(trajs[:1], 0.25, seed=3)
    assert info["mode"] == "time" and fit[0].n == 90 and held[0].n == 30
    assert held[0].t[0] == pytest.approx(fit[0].t[-1] + 0.01)
    # too short to split: the error says how many samples it needs, and the fewest it needs does split
    short = trajs[0].slice(0, 25, "")
    with pytest.raises(RispError, match=r"too short \(25 samples\).*at least 10 samples each at --held-out 0.3: "
                                        r"it needs (\d+)") as e:
        split_trajectories([short], 0.3, seed=3)
    need = int(str(e.value).split("it needs ")[1].split()[0])
    fit_need, held_need, _ = split_trajectories([trajs[0].slice(0, need, "")], 0.3, seed=3)
    assert fit_need[0].n >= 10 and held_need[0].n >= 10
    with pytest.raises(RispError, match="too short"):
        split_trajectories([trajs[0].slice(0, need - 1, "")], 0.3, seed=3)
    # a part shorter than the segment horizon is named, with its length
    model, k = cands.build_model("quadrotor", (), trajs[0].sidecar, trajs[0].dt)
    with pytest.raises(RispError, match=r"segment horizon \(40 samples\): the longest, .*\[held-out\], has 30;"):
        make_segments(model.sim, [held[0]], horizon=40, k=k, params=model.base)


def _drop_rows(src, dst, rows):
    """Copy a synthetic folder with the given data rows removed from every CSV (dropped samples, as in real logs)."""
    import shutil

    dst.mkdir()
    for f in sorted(src.iterdir()):
        if f.suffix == ".csv":
            lines = f.read_text().splitlines(keepends=True)
            (dst / f.name).write_text("".join(l for i, l in enumerate(lines) if i - 1 not in rows))
        elif f.suffix == ".json":
            shutil.copy(f, dst / f.name)


def test_segments_leave_out_dropped_samples_and_uneven_steps(quad_data, tmp_path):
    """The simulator steps at one rate: a segment across a dropped sample (a double step) was simulated as one step,
    and effect-free data came out `unexplained`; such segments are left out, and data without one even segment is
    a clear error."""
    from risp_data.errors import RispError
    from risp_tasks.diagnose.fit import even_starts

    t = np.arange(10) * 0.01
    assert even_starts(t, 3).tolist() == [True] * 7 + [False] * 3
    t_gap = np.delete(np.arange(11) * 0.01, 5)  # sample 5 dropped: the step 4 → 5 is 0.02 s
    assert even_starts(t_gap, 3).tolist() == [True, True, False, False, False, True, True, False, False, False]
    d, _ = quad_data
    _drop_rows(d, tmp_path / "gaps", {40, 80})
    trajs = load_measured([tmp_path / "gaps"], "quadrotor")
    model, k = cands.build_model("quadrotor", (), trajs[0].sidecar, trajs[0].dt)
    seg = make_segments(model.sim, trajs, horizon=10, k=k, stride=1, params=model.base)
    for j, i in zip(seg.traj_index, seg.start):
        steps = np.diff(trajs[j].t[i:i + 11])
        assert np.allclose(steps, trajs[j].dt), (j, i, steps)
    full = make_segments(model.sim, load_measured([d], "quadrotor"), horizon=10, k=k, stride=1, params=model.base)
    assert full.count - 3 * (2 * 10 + 2) <= seg.count < full.count  # per file at most 10 starts per gap, 2 rows fewer
    with pytest.raises(RispError, match="no segment of 101 evenly spaced samples"):
        make_segments(model.sim, trajs, horizon=100, k=k, stride=1, params=model.base)


def _score(name, rss, k, rho, n_eff=1000):
    s = Score(name, tuple(name.split("+")) if name != "base" else (), k, rss, 10 * n_eff, n_eff,
              n_eff * np.log(rss / (10 * n_eff)) + k * np.log(n_eff))
    s.rho = rho
    return s


def test_decision_rule():
    base = _score("base", 20000.0, 0, 2.0)
    good = _score("wind", 10000.0, 3, 1.0)
    weak = _score("air_drag", 19900.0, 1, 1.99)
    assert decide(base, [good, weak], []).cause == "wind"
    # improvement but the residual stays far above the noise floor: never a confident name
    partial = _score("wind", 15000.0, 3, 1.8)
    d = decide(base, [partial, weak], [])
    assert d.cause == "unexplained" and d.best_candidate.name == "wind"
    # nothing helps and the base is at the noise floor
    base_ok = _score("base", 10000.0, 0, 1.05)
    assert decide(base_ok, [_score("wind", 9990.0, 3, 1.05)], []).cause == "none"
    # nothing helps and the base is not at the noise floor
    assert decide(base, [weak], []).cause == "unexplained"
    # a pair replaces its single only when it beats it clearly
    pair = _score("wind+air_drag", 6000.0, 4, 1.0)
    assert decide(base, [good, weak], [pair]).cause == "wind+air_drag"
    pair_marginal = _score("wind+air_drag", 9990.0, 4, 1.0)
    assert decide(base, [good, weak], [pair_marginal]).cause == "wind"
    # the best single *that beats the base* (docs/diagnose.md §6): a one-parameter effect with the lowest BIC that
    # misses the 5 % RSS margin (−4.5 %) does not hide a three-parameter one that beats the base by both (−5.5 %)
    floor = _score("base", 20000.0, 0, 1.4)
    cheap, real = _score("air_drag", 19100.0, 1, 1.3), _score("wind", 18900.0, 3, 1.2)
    assert cheap.bic < real.bic and cheap.rss_reduction(floor) < 0.05 <= real.rss_reduction(floor)
    assert decide(floor, [cheap, real], []).cause == "wind"


def test_unexplained_estimates_name_the_estimate_noise():
    """Issue 10: an `unexplained` verdict on a network's estimates from a video names the estimate noise; other
    verdicts, and data without the `estimated_by` provenance, keep their reason."""
    base, weak = _score("base", 20000.0, 0, 2.0), _score("air_drag", 19900.0, 1, 1.99)
    unexplained = decide(base, [weak], [])
    by = {"task": "risp-task estimate", "model": {"path": "runs/q/model.pt", "sha256": "ab" * 32}}
    noise = {"lag1_correlation_estimate": {"position": 0.0, "velocity": 0.99}}
    noted = estimate_note(unexplained, by, noise)
    assert noted.cause == "unexplained" and noted.reason.startswith(unexplained.reason)
    assert "estimate noise" in noted.reason and "runs/q/model.pt" in noted.reason and "velocity 0.99" in noted.reason
    assert "position" not in noted.reason  # only the groups whose estimated correlation is not zero are quoted
    # odd provenance (a hand-written sidecar): a plain model path, no model, no correlation estimate
    for odd in ({"model": "m.pt"}, {"task": "risp-task estimate"}, ["not", "a", "dict"]):
        reason = estimate_note(unexplained, odd, {}).reason
        assert "estimate noise" in reason and "bias that drifts" in reason
    assert "m.pt" in estimate_note(unexplained, {"model": "m.pt"}, {}).reason
    assert "estimate" not in unexplained.reason  # the plain verdict says nothing of estimates
    assert estimate_note(unexplained, None, noise) == unexplained
    named = decide(base, [_score("wind", 10000.0, 3, 1.0), weak], [])
    assert estimate_note(named, by, noise) == named


def test_wind_on_estimates_gives_the_tilt_it_equals():
    """Issue 10: a `wind` named on a network's estimates says which attitude bias would fit the same force:
    β = atan(|(f_x, f_y)| / (m g)); nothing is added without provenance, for other causes, or without a mass."""
    import math

    base, weak = _score("base", 20000.0, 0, 2.0), _score("air_drag", 19900.0, 1, 1.99)
    named = decide(base, [_score("wind", 10000.0, 3, 1.0), weak], [])
    assert named.cause == "wind"
    by = {"model": {"path": "runs/q/model.pt"}}
    values = {"wind.fx": 3.0, "wind.fy": -4.0, "wind.fz": 9.0}  # f_z is along the thrust: no tilt
    noted = estimate_force_note(named, by, values, 3.0)
    tilt = math.degrees(math.atan(5.0 / (3.0 * 9.81)))
    assert noted.cause == "wind" and noted.reason.startswith(named.reason)
    assert "5.00 N on 3 kg" in noted.reason and f"a tilt of {tilt:.1f}°" in noted.reason and f"{tilt:.1f}" == "9.6"
    assert f"{math.degrees(math.atan(10 / (3 * 9.81))):.1f}°" in estimate_force_note(
        named, by, {"wind.fx": 10.0, "wind.fy": 0.0}, 3.0).reason  # grows with the force
    assert estimate_force_note(named, None, values, 3.0) == named
    assert estimate_force_note(named, by, values, None) == named
    unexplained = decide(base, [weak], [])
    assert estimate_force_note(unexplained, by, values, 3.0) == unexplained
    drag = decide(base, [_score("air_drag", 10000.0, 1, 1.0)], [])
    assert drag.cause == "air_drag" and estimate_force_note(drag, by, values, 3.0) == drag


def _estimated_copy(quad_data, folder, sidecar):
    """Two trajectories of the quadrotor data in ``folder``, one sidecar marked as `risp-task estimate` output."""
    import json
    import shutil

    src, _ = quad_data
    for f in sorted(src.glob("traj_00[01].*")):
        shutil.copy(f, folder / f.name)
    side = folder / sidecar
    side.write_text(json.dumps({**json.loads(side.read_text()), "estimated_by": {"model": {"path": "q.pt"}}}))
    return side


def test_a_wind_verdict_on_estimates_carries_its_tilt_through_diagnose(quad_data, tmp_path, monkeypatch):
    """The note reaches the report through run._diagnose, with the fitted force and the data's own mass (the
    decision is forced to the fitted `wind` model, and kept there past the residual-dependence check)."""
    import math

    from risp_tasks.diagnose import run as diagnose_run
    from risp_tasks.diagnose.run import DiagnoseConfig, diagnose
    from risp_tasks.diagnose.select import Decision

    _estimated_copy(quad_data, tmp_path, "traj_000.json")
    monkeypatch.setattr(diagnose_run, "decide", lambda base, singles, pairs: Decision(
        "wind", next(s for s in singles if s.name == "wind"), None, "forced"))
    monkeypatch.setattr(diagnose_run, "check_dependence", lambda decision, dependence: decision)
    report = diagnose(DiagnoseConfig(data=(str(tmp_path),), env="quadrotor", out=None, seed=0, effects=("wind",),
                                     max_iters=2, progress=False, plots=False))
    p, m = report["parameters"], report["fixed_parameters"]["mass"]
    f_h = math.hypot(p["wind.fx"]["value"], p["wind.fy"]["value"])
    assert report["cause"] == "wind" and report["reason"].startswith("forced")
    assert f"({f_h:.2f} N on {m:.3g} kg) equals a tilt of {math.degrees(math.atan(f_h / (m * 9.81))):.1f}°" in report["reason"]


def test_diagnose_passes_the_estimates_provenance_on(quad_data, tmp_path, monkeypatch):
    """The sidecar's `estimated_by` reaches the verdict through the whole diagnose run (run._diagnose); the
    decision itself is forced to `unexplained`, as the motor-lag data would otherwise be named."""
    import json

    from risp_tasks.diagnose import run as diagnose_run
    from risp_tasks.diagnose.run import DiagnoseConfig, diagnose
    from risp_tasks.diagnose.select import Decision

    side = _estimated_copy(quad_data, tmp_path, "traj_001.json")
    monkeypatch.setattr(diagnose_run, "decide", lambda base, singles, pairs: Decision(
        "unexplained", base, None, "forced"))
    cfg = DiagnoseConfig(data=(str(tmp_path),), env="quadrotor", out=None, seed=0, effects=("wind",), max_iters=2,
                         progress=False, plots=False)
    report = diagnose(cfg)
    assert report["cause"] == "unexplained" and report["reason"].startswith("forced")
    assert "; the data are a network's estimates from a video (risp-task estimate, model q.pt)" in report["reason"]
    side.write_text(json.dumps({k: v for k, v in json.loads(side.read_text()).items() if k != "estimated_by"}))
    plain = diagnose(cfg)["reason"]  # without provenance: the decision's own reason (and its dependence note)
    assert plain.startswith("forced") and "estimate" not in plain


def test_wind_bounds_scale_with_weight_and_bound_values_are_flagged():
    """Issue 12: a 15.9 N wind on a 2.6 kg vehicle was clipped at a fixed ±15 N bound without a word."""
    from risp_tasks.diagnose.candidates import build_model
    from risp_tasks.diagnose.select import bound_flag
    from risp_tasks.measured import Sidecar

    sc = Sidecar("quadrotor", {"env": "quadrotor", "mass": 2.6}, "test")
    model, _ = build_model("quadrotor", ("wind",), sc, 0.01)
    i = model.free.index("wind.fx")
    limit = 1.5 * 2.6 * 9.81  # plausible ±0.5·m·g widened by its width
    assert float(model.upper[i]) == pytest.approx(limit, rel=1e-6) and float(model.lower[i]) == pytest.approx(-limit, rel=1e-6)
    assert bound_flag(model, "wind.fx", 15.9) == {}
    assert bound_flag(model, "wind.fx", float(model.upper[i]))["at_bound"] == "upper"
    assert bound_flag(model, "wind.fx", float(model.lower[i]))["at_bound"] == "lower"


def test_grid_start_scans_each_effect_parameter_over_its_plausible_range(quad_data):
    """Each effect parameter in turn goes to the bin midpoint of its plausible range nearest its optimum."""
    d, _ = quad_data
    trajs = load_measured([str(d)], "quadrotor")
    model, _ = cands.build_model("quadrotor", ("motor_lag", "air_drag"), trajs[0].sidecar, trajs[0].dt)
    spec = model.sim.spec.available_effects
    expected = [cands.scaled_range("quadrotor", e, *map(float, spec[e].ranges[0]), trajs[0].sidecar)
                for e in ("motor_lag", "air_drag")]
    assert [tuple(r) for r in model.plausible] == expected
    target = torch.tensor([lo + 0.8 * (hi - lo) for lo, hi in expected], dtype=torch.float64)
    width = torch.tensor([hi - lo for lo, hi in expected], dtype=torch.float64)
    fn = lambda z: (model.params(z)[model.free_index] - target) / width  # noqa: E731
    z0 = torch.zeros(2, dtype=torch.float64)
    with torch.no_grad():
        r0 = fn(z0)
    z, r, rss = grid_start(model, fn, z0, r0, float((r0**2).sum()))
    theta = model.params(z)[model.free_index]
    for j, (lo, hi) in enumerate(expected):
        # 0.8 of the range lies between the midpoints 0.6875 and 0.8125: the nearer, 0.8125, wins
        assert float(theta[j]) == pytest.approx(lo + 0.8125 * (hi - lo), rel=1e-9)
    assert rss == pytest.approx(float((r**2).sum())) and rss < float((r0**2).sum())


def test_fit_runs_from_two_starts_and_keeps_the_lower_loss(quad_data, monkeypatch):
    import risp_tasks.diagnose.fit as fit

    d, _ = quad_data
    trajs = load_measured([str(d)], "quadrotor")
    model, k = cands.build_model("quadrotor", ("motor_lag",), trajs[0].sidecar, trajs[0].dt)
    obs = Observer(model.sim)
    seg = make_segments(model.sim, trajs, horizon=5, k=k, params=model.base)
    sigma = channel_sigma(obs, estimate_noise(model.sim, trajs))
    lo, hi = model.plausible[0]
    model.base[model.free_index[0]] = hi + 0.9 * (hi - lo)  # a poor default: the scan finds a better start
    runs = []
    real = fit._levenberg_marquardt

    def recording(model_, fn, z, *args, **kwargs):
        out = real(model_, fn, z, *args, **kwargs)
        runs.append((z.clone(), out[2]))
        return out

    monkeypatch.setattr(fit, "_levenberg_marquardt", recording)
    result = fit.fit_model(model, obs, seg, sigma, fit.FitConfig(horizon=5, max_iters=3))
    assert len(runs) == 2
    assert torch.equal(runs[0][0], torch.zeros(1, dtype=torch.float64)) and not torch.equal(runs[1][0], runs[0][0])
    assert result.rss == min(rss for _, rss in runs)
    with torch.no_grad():
        assert result.rss == pytest.approx(float((residuals(model.sim, obs, result.params, seg, sigma) ** 2).sum()))


def test_a_report_rewritten_without_plots_links_none_and_keeps_no_old_ones(quad_data, tmp_path, monkeypatch):
    """diagnose into a folder that holds an earlier report: with --no-plots the new report.md links no plots, and
    the earlier run's PNGs are gone (they would pass for this run's)."""
    from risp_tasks.diagnose import run as diagnose_run
    from risp_tasks.diagnose.report import PLOTS
    from risp_tasks.diagnose.run import DiagnoseConfig, diagnose
    from risp_tasks.diagnose.select import Decision

    _estimated_copy(quad_data, tmp_path, "traj_000.json")
    monkeypatch.setattr(diagnose_run, "decide", lambda base, singles, pairs: Decision(
        "unexplained", base, None, "forced"))
    out = tmp_path / "rep"
    cfg = dict(data=(str(tmp_path),), env="quadrotor", out=str(out), seed=0, effects=("wind",), max_iters=2,
               progress=False)
    diagnose(DiagnoseConfig(**cfg, plots=True))
    assert all((out / fn).is_file() for fn in PLOTS.values())
    assert all(f"]({fn})" in (out / "report.md").read_text() for fn in PLOTS.values())
    diagnose(DiagnoseConfig(**cfg, plots=False))
    text = (out / "report.md").read_text()
    assert "none (run with --no-plots)" in text and "![" not in text
    assert not any((out / fn).exists() for fn in PLOTS.values())


def test_held_out_errors_convert_thrusts_at_the_models_own_k_f(quad_data):
    """one_step and rollout_error turned measured thrusts into commands at the simulator's default k_f while the
    model simulated with its own (a sidecar may fix k_f): a model with another k_f was scored with the wrong thrust.
    At the model's own k_f the simulated thrust is the measured one, so the scores barely move with k_f (measured:
    +3 % one-step RMS, +5 % rollout for k_f × 1.5; with the default k_f's conversion ×2.0 and ×2.4)."""
    from risp_tasks.diagnose.residuals import one_step, rollout_error

    d, _ = quad_data
    trajs = load_measured([str(d)], "quadrotor")
    assert trajs[0].thrust is not None  # a thrust log: the case that is converted
    model, k = cands.build_model("quadrotor", (), trajs[0].sidecar, trajs[0].dt)
    obs = Observer(model.sim)
    p = model.base.clone()
    q = p.clone()
    q[model.sim.param_index("k_f")] *= 1.5
    rms = [float(np.sqrt((one_step(model.sim, obs, x, trajs, k, seed=0).error ** 2).mean())) for x in (p, q)]
    assert rms[1] < 1.2 * rms[0], rms
    roll = [rollout_error(model.sim, obs, x, trajs, k, 10, seed=0)["normalized"] for x in (p, q)]
    assert roll[1] < 1.2 * roll[0], roll


@pytest.mark.parametrize("env", ["hand", "rod"])
def test_a_fixed_step_simulator_refuses_a_sample_interval_it_cannot_step(env):
    """The hand and the rod integrate with a fixed 10 ms step (their module's DT): a 30 Hz log used to get an
    instance step of 11.1 ms that they never read, and ran 30 ms of simulation per 33.3 ms sample without a word."""
    from risp_tasks.diagnose.adapter import matched_simulator
    from risp_tasks.sims import get_simulator

    sim = get_simulator(env)
    assert matched_simulator(sim, 0.02)[1] == 2 and matched_simulator(sim, 0.0100001)[1] == 1
    with pytest.raises(RispError, match=rf"the {env} simulator steps a fixed 0.01 s: the data's sample interval "
                                        r"0.0333333 s is not a whole number of steps"):
        matched_simulator(sim, 1 / 30)
    assert sim.dt == 0.01  # the instance is left as it was
