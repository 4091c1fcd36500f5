"""Shared helpers of the diagnose tests: synthetic data with a hidden effect, then the full pipeline."""

from __future__ import annotations

from risp_tasks.diagnose.run import DiagnoseConfig, diagnose
from risp_tasks.diagnose.synth import SynthConfig, make_synthetic
from risp_tasks.sims import available_effects

#: Stated tolerance of the recovered parameters: relative error ≤ 25 % for every parameter whose true
#: value exceeds 10 % of its plausible range; otherwise an absolute error ≤ 10 % of the range width.
REL_TOL = 0.25
ABS_TOL_OF_RANGE = 0.10


def run_case(tmp_path, env, effect, seed, n_traj=4, samples=300, pairs_top=2, out=True, max_iters=25):
    data = tmp_path / "data"
    truth = make_synthetic(SynthConfig(env=env, seed=seed, n_traj=n_traj, samples=samples, effect=effect), data)
    report = diagnose(DiagnoseConfig(data=(str(data),), env=env, out=str(tmp_path / "report") if out else None,
                                     seed=seed, pairs_top=pairs_top, progress=False, plots=out, max_iters=max_iters))
    return truth, report


def assert_recovered(env, truth, report):
    assert report["cause"] == truth["effect"], (report["cause"], report["reason"], report["ranking"][:3])
    effects = available_effects(env)
    eff = effects[truth["effect"]]
    for (pname, (lo, hi)) in zip(eff.param_names, eff.ranges):
        name = f"{truth['effect']}.{pname}"
        true = truth["parameters"][name]
        got = report["parameters"][name]
        assert got["std"] is not None and got["std"] > 0
        width = hi - lo
        if abs(true) > 0.1 * width:
            assert abs(got["value"] - true) <= REL_TOL * abs(true), (name, true, got)
        else:
            assert abs(got["value"] - true) <= ABS_TOL_OF_RANGE * width, (name, true, got)
