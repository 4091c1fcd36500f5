"""The fast Jacobian path (issue 9) gives the legacy path's image and J on the same seed.

Tolerance (docs/rendering.md, "The fast Jacobian path"): float32 rounding.  The merged colour passes
compute every channel with the same operations as the per-ψ passes, and the emitter-split primal
sums L = Σ_j ψ_j L_j in another order than the single primal, so per pixel the two paths differ by a few
float32 ulps of the radiance that flows through that pixel: asserted as ‖J_fast − J_legacy‖_F ≤ RTOL ·
‖J_legacy‖_F per ψ_j with RTOL = 1e-5 (measured ≈ 1e-7), plus bitwise-zero off-channel entries of the
colour Jacobians (they are never computed on the fast path; on the legacy path they are exact zeros).
"""

from __future__ import annotations

import numpy as np
import pytest

from risp_data.envs import ENV_NAMES, get_environment
from risp_data.errors import RispError
from risp_data.psi import DOMAINS, sample_rendering
from risp_data.render import JacobianPlan, plan_jacobian

RES, SPP = 16, 4
RTOL = 1e-5
_RENDERERS: dict = {}


def renderer(env: str, domain: str):
    from risp_data.render import Renderer

    if (env, domain) not in _RENDERERS:
        _RENDERERS[env, domain] = Renderer(env, domain, resolution=RES, spp=SPP)
    return _RENDERERS[env, domain]


def _compare(env: str, domain: str, seed: int) -> None:
    r = renderer(env, domain)
    rng = np.random.default_rng(seed)
    state = get_environment(env).sample_states(rng, 1)[0]
    config = sample_rendering(env, domain, rng)
    img_f, J_f = r.render(state, config, seed=seed, jacobian_path="fast")
    img_l, J_l = r.render(state, config, seed=seed, jacobian_path="legacy")
    assert J_f.shape == J_l.shape == (len(r.psi_names), RES, RES, 3) and J_f.dtype == np.float32
    plan = r.jacobian_plan(config.psi, config.aux)
    assert plan.emitter == (0, 1) and plan.groups == ((2, 3, 4), (5, 6, 7)) and plan.single == ()  # 4 passes
    assert np.linalg.norm(img_f - img_l) <= RTOL * np.linalg.norm(img_l)
    for j, name in enumerate(r.psi_names):
        norm = np.linalg.norm(J_l[j])
        assert norm > 1e-4, name  # the comparison is not between two zero images
        assert np.linalg.norm(J_f[j] - J_l[j]) <= RTOL * norm, (name, np.linalg.norm(J_f[j] - J_l[j]) / norm)
    for group in plan.groups:
        for c, j in enumerate(group):
            off = [c2 for c2 in range(3) if c2 != c]
            assert np.all(J_l[j][..., off] == 0) and np.all(J_f[j][..., off] == 0)
    # a different seed is a different image: the comparison above is sensitive to the seed
    img_o, _ = r.render(state, config, seed=seed + 1, jacobian=False)
    assert np.abs(img_o - img_l).max() > 1e-3


@pytest.mark.parametrize("domain", DOMAINS)
def test_fast_jacobian_equals_legacy_cube(domain):
    _compare("cube", domain, seed=3)


@pytest.mark.slow
@pytest.mark.parametrize("domain", DOMAINS)
@pytest.mark.parametrize("env", [e for e in ENV_NAMES if e != "cube"])
def test_fast_jacobian_equals_legacy(env, domain):
    _compare(env, domain, seed=4)


def test_unknown_jacobian_path():
    from risp_data.render import Renderer

    with pytest.raises(RispError, match="fast, legacy"):
        Renderer("cube", jacobian_path="quick")
    r = renderer("cube", "train")
    env = get_environment("cube")
    rng = np.random.default_rng(0)
    with pytest.raises(RispError, match="fast, legacy"):
        r.render(env.sample_states(rng, 1)[0], sample_rendering("cube", "train", rng), seed=0, jacobian_path="x")


# ------------------------------------------------------------------- the plan (pure numpy, no renders)

NAMES = ("light_intensity", "ambient", "object_r", "object_g", "object_b")
KINDS = ["color", "float", "color"]  # bindings: light radiance, ambient scale, object reflectance


def _T(light=(2.0, 2.0, 2.0), obj_cross=0.0):
    """Tangents T[j][k] of a tiny scene: light ← ψ_0, ambient ← ψ_1, object colour ← ψ_2..4."""
    z3 = np.zeros(3)
    T = [[np.asarray(light, float), np.zeros(()), z3], [z3, np.ones(()), z3]]
    for c in range(3):
        t = np.zeros(3)
        t[c] = 1.0
        t[(c + 1) % 3] = obj_cross  # a channel-mixing binding (not the rgb variant's reflectances)
        T.append([z3, np.zeros(()), t])
    return T


def test_plan_merges_own_channel_colours_and_splits_emitters():
    plan = plan_jacobian(NAMES, _T(), KINDS, emitters=[0, 1], all_emitters_bound=True)
    assert plan == JacobianPlan(emitter=(0, 1), groups=((2, 3, 4),), single=())


def test_plan_falls_back_where_a_step_would_not_be_exact():
    # a colour tangent that leaks into another channel: one pass per channel
    assert plan_jacobian(NAMES, _T(obj_cross=0.5), KINDS, [0, 1], True).single == (2, 3, 4)
    # an emitter the bindings do not cover (a fixed light): I ≠ Σ ψ_j ∂I/∂ψ_j, no emitter split
    plan = plan_jacobian(NAMES, _T(), KINDS, [0, 1], all_emitters_bound=False)
    assert plan.emitter == () and plan.single == (0, 1) and plan.groups == ((2, 3, 4),)
    # a ψ that moves an emitter and a material: neither it nor the other emitters are split
    T = _T()
    T[2][0] = np.ones(3)
    plan = plan_jacobian(NAMES, T, KINDS, [0, 1], True)
    assert plan.emitter == () and 2 in plan.single


def test_render_job_paths_agree_and_bad_path_is_one_error_line(tmp_path, capsys):
    """``risp-data render --jacobian-path fast|legacy``: the same samples to float32 rounding; an unknown
    path is refused with one error line before anything is written."""
    from click.testing import CliRunner

    from risp_data.cli import cli
    from risp_data.shards import ZarrDataset

    def render(out, path):
        args = ["render", "--env", "hand", "--domain", "target", "--res", "8", "--spp", "2", "--quiet", "--n", "2",
                "--shard-size", "2", "--workers", "1", "--format", "zarr", "--jacobian-path", path, "--out", str(out)]
        return CliRunner().invoke(cli, args)

    assert render(tmp_path / "f", "fast").exit_code == 0
    assert render(tmp_path / "l", "legacy").exit_code == 0
    f, l = ZarrDataset(str(tmp_path / "f")), ZarrDataset(str(tmp_path / "l"))
    for i in range(2):
        np.testing.assert_array_equal(f[i]["psi"], l[i]["psi"])
        for j in range(f[i]["jacobian"].shape[0]):
            Jf, Jl = f[i]["jacobian"][j], l[i]["jacobian"][j]
            assert np.linalg.norm(Jf - Jl) <= RTOL * np.linalg.norm(Jl)
    # the console script's path (run_cli: click's usage lines become one line, exit 1)
    from tests.cli_helpers import console_error_line

    line = console_error_line(cli, ["render", "--env", "hand", "--n", "2", "--jacobian-path", "slow", "--out",
                                    str(tmp_path / "x")], capsys)
    assert "--jacobian-path" in line, line
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("domain", DOMAINS)
def test_lean_prb_passes_match_prb(domain):
    """risp_data/prb_passes.py against prb itself on one sample: Σ_e L_e = prb's primal L, and the lean
    forward pass = prb's forward pass (state_in = that L) for a tangent on every ψ-dependent parameter."""
    import drjit as dr
    import mitsuba as mi

    from risp_data.prb_passes import forward_materials, sample_per_emitter

    r = renderer("cube", domain)
    rng = np.random.default_rng(8)
    state, config = get_environment("cube").sample_states(rng, 1)[0], sample_rendering("cube", domain, rng)
    r.set_state(state)
    r.set_config(config.psi, config.aux, track=True)
    r.params.update()
    integ, scene, s = r.integrator, r.scene, r.settings
    with dr.suspend_grad():
        sampler, _ = integ.prepare(scene.sensors()[0], r._var(9, np.uint32), SPP * s.spp_factor, [])
        ray, _, _ = integ.sample_rays(scene, scene.sensors()[0], sampler)
        kw = dict(scene=scene, ray=ray, depth=mi.UInt32(0), active=mi.Bool(True), δL=None)
        L, _, _, _ = integ.sample(mode=dr.ADMode.Primal, sampler=sampler.clone(), state_in=None, **kw)
        Ls = sample_per_emitter(scene, sampler.clone(), ray, list(scene.emitters()), s.max_depth, s.rr_depth)
        with dr.resume_grad():
            for leaf in r._leaves:  # a tangent on every ψ-dependent parameter at once
                dr.set_grad(leaf, 0.5)
        ref, _, _, _ = integ.sample(mode=dr.ADMode.Forward, sampler=sampler.clone(), state_in=L, δaovs=None, **kw)
        lean = forward_materials(scene, sampler.clone(), ray, L, s.max_depth, s.rr_depth)
        L, total, ref, lean = (np.array(x, np.float64) for x in (L, sum(Ls[1:], Ls[0]), ref, lean))
    assert np.abs(L).max() > 0 and np.abs(ref).max() > 0
    np.testing.assert_allclose(total, L, rtol=1e-5, atol=1e-6 * np.abs(L).max())
    np.testing.assert_allclose(lean, ref, rtol=1e-5, atol=1e-6 * np.abs(ref).max())
