"""Rendering parameters ψ (issue 2, item 3) and the Mitsuba renderer with forward-mode Jacobians (item 4).

Tolerances (docs/rendering.md):
- Jacobian: J_j against the central difference (I(ψ + ε e_j) − I(ψ − ε e_j)) / 2ε rendered with the same
  seed, ε = 1e-2; relative error ‖J_j − FD_j‖_F / ‖FD_j‖_F below JAC_RTOL = 1e-3 (measured ≈1e-5: the
  float32 rounding of the images divided by 2ε).
- Determinism: the same (state, config, seed) gives the same image and J; bitwise on the LLVM backend
  in our runs, asserted to DET_ATOL = 1e-6.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from risp_data.envs import ENV_NAMES, get_environment
from risp_data.envs.meshes import project
from risp_data.errors import RispError
from risp_data.mitsuba_setup import init_mitsuba
from risp_data.psi import (
    DOMAINS,
    FLOOR_RANGE,
    OBJECT_RANGE,
    RenderConfig,
    nominal_rendering,
    psi_specs,
    sample_rendering,
)

RES, SPP = 16, 4
JAC_EPS, JAC_RTOL = 1e-2, 1e-3
DET_ATOL = 1e-6
_RENDERERS: dict = {}


def renderer(env: str, domain: str = "train", res: int = RES):
    """Renderers are cached per module: building one compiles kernels (seconds on 2 cores)."""
    from risp_data.render import Renderer

    key = (env, domain, res)
    if key not in _RENDERERS:
        _RENDERERS[key] = Renderer(env, domain, resolution=res, spp=SPP)
    return _RENDERERS[key]


# ---------------------------------------------------------------------------------------------- ψ


@pytest.mark.parametrize("env", ENV_NAMES)
def test_psi_specs(env):
    specs = psi_specs(env)
    assert 6 <= len(specs) <= 10
    names = [s.name for s in specs]
    assert len(set(names)) == len(names)
    assert all(re.fullmatch(r"[a-z0-9_]+", n) for n in names)
    for required in ("light_intensity", "ambient", "object_r", "object_g", "object_b", "floor_r", "floor_g", "floor_b"):
        assert required in names
    assert all(s.low <= s.nominal <= s.high and s.low < s.high for s in specs)
    for domain in DOMAINS:
        nominal = nominal_rendering(env, domain)
        assert nominal.psi.shape == (len(specs),)
        json.dumps(nominal.aux)


@pytest.mark.parametrize("env", ENV_NAMES)
def test_sample_rendering_ranges_and_determinism(env):
    specs = psi_specs(env)
    low, high = np.array([s.low for s in specs]), np.array([s.high for s in specs])
    names = [s.name for s in specs]
    train = [sample_rendering(env, "train", np.random.default_rng(i)) for i in range(50)]
    psi = np.stack([c.psi for c in train])
    assert np.all(psi >= low) and np.all(psi <= high)
    assert psi.std(0).min() > 0.01  # every ψ is randomised
    again = sample_rendering(env, "train", np.random.default_rng(3))
    np.testing.assert_array_equal(again.psi, train[3].psi)
    assert again.aux == train[3].aux
    assert len({c.aux["floor_texture"] for c in train}) > 1
    # target: colours outside the training ranges, same ψ layout, JSON aux
    for i in range(50):
        c = sample_rendering(env, "target", np.random.default_rng(i))
        assert c.psi.shape == psi.shape[1:]
        json.dumps(c.aux)
        obj = c.psi[names.index("object_r"):names.index("object_b") + 1]
        floor = c.psi[names.index("floor_r"):names.index("floor_b") + 1]
        assert np.all((obj < OBJECT_RANGE[0]) | (obj > OBJECT_RANGE[1]))
        assert np.all((floor < FLOOR_RANGE[0]) | (floor > FLOOR_RANGE[1]))
        assert np.all((obj > 0) & (obj < 1) & (floor > 0) & (floor < 1))


def test_psi_errors():
    with pytest.raises(RispError, match="quadrotor, cube, hand, rod"):
        psi_specs("boat")
    with pytest.raises(RispError, match="train, target"):
        sample_rendering("cube", "test", np.random.default_rng(0))
    with pytest.raises(RispError, match="train, target"):
        nominal_rendering("cube", "eval")
    with pytest.raises(RispError, match="Generator"):
        sample_rendering("cube", "train", 0)


# ------------------------------------------------------------------------------------------ Mitsuba


def test_init_mitsuba():
    variant = init_mitsuba()
    assert variant in ("llvm_ad_rgb", "cuda_ad_rgb")
    assert init_mitsuba() == variant  # idempotent
    import mitsuba as mi

    assert mi.variant() == variant
    with pytest.raises(RispError, match="llvm_ad_rgb, cuda_ad_rgb"):
        init_mitsuba("scalar_spectral")


def test_init_mitsuba_without_llvm(monkeypatch):
    """No libLLVM: the LLVM variant (asked for, or picked for want of a GPU) fails with the LLVM error's one
    line; a CUDA machine would go on without it (checked on a GPU by benchmarks/gpu_check.py)."""
    from risp_data import mitsuba_setup

    def no_llvm():
        raise RispError("no libLLVM >= 16 found for Dr.Jit's CPU backend (found: none)")

    monkeypatch.setattr(mitsuba_setup, "ensure_llvm", no_llvm)
    monkeypatch.setattr(mitsuba_setup, "_CHOSEN", None)
    with pytest.raises(RispError, match="no libLLVM"):
        mitsuba_setup.init_mitsuba("llvm_ad_rgb")
    monkeypatch.setattr(mitsuba_setup, "_cuda_usable", lambda: False)
    monkeypatch.setattr(mitsuba_setup, "_cuda_driver_present", lambda: False)
    with pytest.raises(RispError, match="no libLLVM"):
        mitsuba_setup.init_mitsuba()
    monkeypatch.setattr(mitsuba_setup, "_cuda_driver_present", lambda: True)  # a driver but no usable GPU
    with pytest.raises(RispError, match="no libLLVM"):
        mitsuba_setup.init_mitsuba()
    with pytest.raises(RispError, match="needs a usable CUDA GPU"):
        mitsuba_setup.init_mitsuba("cuda_ad_rgb")
    # asked for by name, the error quotes Dr.Jit's own reason (it said only "none was found")
    monkeypatch.setattr(mitsuba_setup, "_cuda_problem", lambda: "RuntimeError: cuInit() failed: CUDA_ERROR_NO_DEVICE")
    with pytest.raises(RispError, match=r"needs a usable CUDA GPU; RuntimeError: cuInit\(\) failed: CUDA_ERROR_NO_DEVICE"):
        mitsuba_setup.init_mitsuba("cuda_ad_rgb")


def _fd_check(r, state, config, seed):
    """Relative error of every J_j against same-seed central differences; also returns ‖FD_j‖."""
    image, J = r.render(state, config, seed=seed)
    errors, norms = [], []
    for j in range(len(r.psi_names)):
        plus, minus = config.psi.copy(), config.psi.copy()
        plus[j] += JAC_EPS
        minus[j] -= JAC_EPS
        ip, _ = r.render(state, RenderConfig(plus, config.aux), seed=seed, jacobian=False)
        im, _ = r.render(state, RenderConfig(minus, config.aux), seed=seed, jacobian=False)
        fd = (ip.astype(np.float64) - im) / (2 * JAC_EPS)
        norms.append(np.linalg.norm(fd))
        errors.append(np.linalg.norm(J[j] - fd) / max(norms[-1], 1e-12))
    return image, J, np.array(errors), np.array(norms)


@pytest.mark.slow
@pytest.mark.parametrize("domain", DOMAINS)
@pytest.mark.parametrize("env", ENV_NAMES)
def test_render_and_jacobian_match_finite_differences(env, domain):
    """Every environment renders in both domains, and J_j = ∂I/∂ψ_j matches central differences for
    every ψ_j (same seed for all renders)."""
    r = renderer(env, domain)
    rng = np.random.default_rng(11)
    state = get_environment(env).sample_states(rng, 1)[0]
    config = sample_rendering(env, domain, rng)
    image, J, errors, norms = _fd_check(r, state, config, seed=5)
    K = len(r.psi_names)
    assert image.shape == (RES, RES, 3) and image.dtype == np.float32
    assert J.shape == (K, RES, RES, 3) and J.dtype == np.float32
    assert np.isfinite(image).all() and np.isfinite(J).all()
    assert image.std() > 1e-3 and image.max() > 0.01  # not constant, not black
    assert np.all(norms > 1e-4), dict(zip(r.psi_names, norms))  # every ψ_j changes the image
    assert np.all(errors < JAC_RTOL), dict(zip(r.psi_names, errors))


def test_render_is_deterministic():
    r = renderer("cube")
    env = get_environment("cube")
    rng = np.random.default_rng(0)
    states = env.sample_states(rng, 2)
    configs = [sample_rendering("cube", "train", rng) for _ in range(2)]
    a_img, a_J = r.render(states[0], configs[0], seed=42)
    r.render(states[1], configs[1], seed=43)  # something else in between
    b_img, b_J = r.render(states[0], configs[0], seed=42)
    np.testing.assert_allclose(b_img, a_img, rtol=0, atol=DET_ATOL)
    np.testing.assert_allclose(b_J, a_J, rtol=0, atol=DET_ATOL)
    c_img, _ = r.render(states[0], configs[0], seed=43)
    assert np.abs(c_img - a_img).max() > 1e-3  # another seed → other Monte Carlo noise
    p_img, none = r.render(states[0], configs[0], seed=42, jacobian=False)
    assert none is None
    np.testing.assert_allclose(p_img, a_img, rtol=0, atol=DET_ATOL)


def test_render_is_deterministic_across_renderer_instances():
    """docs/rendering.md: the same (state, config, seed) gives the same image and J in a fresh Renderer."""
    from risp_data.render import Renderer

    env = get_environment("cube")
    rng = np.random.default_rng(5)
    state, config = env.sample_states(rng, 1)[0], sample_rendering("cube", "train", rng)
    a_img, a_J = renderer("cube").render(state, config, seed=7)
    b_img, b_J = Renderer("cube", "train", resolution=RES, spp=SPP).render(state, config, seed=7)
    np.testing.assert_allclose(b_img, a_img, rtol=0, atol=DET_ATOL)
    np.testing.assert_allclose(b_J, a_J, rtol=0, atol=DET_ATOL)


def test_renderer_reuses_compiled_kernels():
    """After warm-up, new states, ψ and seeds launch only kernels served from Dr.Jit's in-memory kernel
    cache: no new code generation or compilation per sample (docs/rendering.md).  (Which kernels a
    render launches can vary with Dr.Jit's lazy evaluation of earlier updates, so only compilation is
    asserted, not the exact kernel set.)"""
    import drjit as dr

    r = renderer("cube")
    env = get_environment("cube")
    rng = np.random.default_rng(6)
    states = env.sample_states(rng, 4)
    # New states, ψ values and seeds; the discrete randomization (floor texture kind, …) is held fixed
    # because switching it legitimately selects other kernels.
    sampled = [sample_rendering("cube", "train", rng) for _ in range(4)]
    configs = [RenderConfig(psi=c.psi, aux=sampled[0].aux) for c in sampled]
    assert not np.allclose(configs[0].psi, configs[1].psi)
    for i in range(2):  # warm-up: the first renders may compile
        r.render(states[i], configs[i], seed=100 + i)
    was_on = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for i in range(2, 4):
            dr.kernel_history_clear()
            r.render(states[i], configs[i], seed=100 + i)
            jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
            assert jit, "kernel history recorded no JIT kernel"
            fresh = [k["hash"] for k in jit if not k["cache_hit"] or k["cache_disk"]]
            assert not fresh, f"kernels compiled or loaded from disk again: {fresh}"
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was_on)
        dr.kernel_history_clear()


def test_camera_projection_matches_mitsuba():
    """The cube's silhouette centroid in a render is where meshes.project puts the cube centre."""
    res = 32
    r = renderer("cube", res=res)
    env = get_environment("cube")
    config = nominal_rendering("cube")
    psi = config.psi.copy()
    psi[r.psi_names.index("ambient")] = 0.0
    for name in ("floor_r", "floor_g", "floor_b"):
        psi[r.psi_names.index(name)] = 0.0
    aux = dict(config.aux, light_direction=[0.0, -1.0, 1.0])  # light from the camera side
    for state in ([0.35, 0.1, 0.7, 0.3, 0.2, 0.1], [-0.4, -0.3, 0.25, 1.0, 0.0, 0.5]):
        image, _ = r.render(np.array(state), RenderConfig(psi, aux), seed=0, jacobian=False)
        mask = image.sum(-1) > 1e-4
        rows, cols = np.nonzero(mask)
        assert mask.sum() > 4
        u, v = project(env.camera, np.array(state[:3]))
        assert abs((cols.mean() + 0.5) / res - u) < 1.5 / res
        assert abs((rows.mean() + 0.5) / res - v) < 1.5 / res


def test_renderer_bad_input():
    r = renderer("cube")
    state = get_environment("cube").sample_states(np.random.default_rng(0), 1)[0]
    config = nominal_rendering("cube")
    with pytest.raises(RispError, match="state must have shape"):
        r.render(state[:5], config, seed=0)
    with pytest.raises(RispError, match="NaN"):
        r.render(np.full(6, np.nan), config, seed=0)
    with pytest.raises(RispError, match="psi must have shape"):
        r.render(state, RenderConfig(config.psi[:3], config.aux), seed=0)
    with pytest.raises(RispError, match="NaN"):
        r.render(state, RenderConfig(np.full(8, np.nan), config.aux), seed=0)
    with pytest.raises(RispError, match="seed"):
        r.render(state, config, seed=-1)
    with pytest.raises(RispError, match="light_distance"):
        aux = {k: v for k, v in config.aux.items() if k != "light_distance"}
        r.render(state, RenderConfig(config.psi, aux), seed=0)
    with pytest.raises(RispError, match="floor texture"):
        r.render(state, RenderConfig(config.psi, dict(config.aux, floor_texture="lava")), seed=0)
    image, _ = r.render(state, config, seed=0, jacobian=False)  # still usable afterwards
    assert np.isfinite(image).all()
    from risp_data.render import Renderer

    with pytest.raises(RispError, match="train, target"):
        Renderer("cube", "eval")
    with pytest.raises(RispError, match="quadrotor, cube, hand, rod"):
        Renderer("boat")
    with pytest.raises(RispError, match="resolution"):
        Renderer("cube", resolution=0)
    with pytest.raises(RispError, match="spp"):
        Renderer("cube", spp=0)


def test_target_reference_images_use_another_integrator_with_the_same_expectation():
    """Jacobian-free target-domain images come from Mitsuba's `path` (Russian roulette), not `prb`:
    deterministic per seed, different noise, the same expected image (checked on the image mean)."""
    from risp_data.render import Renderer

    r = Renderer("cube", "target", resolution=16, spp=16)
    assert r.image_integrator == "path" and r.settings.integrator == "prb"
    env = get_environment("cube")
    rng = np.random.default_rng(11)
    state, config = env.sample_states(rng, 1)[0], sample_rendering("cube", "target", rng)
    ref_a = r.render_reference(state, config, seed=3)
    ref_b = r.render_reference(state, config, seed=3)
    prb, _ = r.render(state, config, seed=3, jacobian=False)
    assert ref_a.shape == prb.shape == (16, 16, 3) and np.isfinite(ref_a).all()
    np.testing.assert_array_equal(ref_a, ref_b)
    assert not np.allclose(ref_a, prb)  # another integrator: other paths, other noise
    assert abs(ref_a.mean() - prb.mean()) < 0.1 * prb.mean()
    # train domain: the reference image is the prb image itself
    t = Renderer("cube", "train", resolution=16, spp=4)
    cfg = sample_rendering("cube", "train", rng)
    np.testing.assert_array_equal(t.render_reference(state, cfg, seed=1), t.render(state, cfg, seed=1, jacobian=False)[0])
