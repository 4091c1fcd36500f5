"""Cube simulator: contact physics against the closed forms of docs/models.md §3, and gradient checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.special import spence
from torch.autograd import gradcheck

from risp_data.envs.rotations import euler_to_quat
from risp_data.errors import RispError
from risp_tasks.sims import get_simulator
from risp_tasks.sims._rigid import quat_outer, rotation_matrix
from risp_tasks.sims.cube import EFFECTS, CubeSimulator, rest_penetration

G = 9.81



pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _t(x):
    return torch.tensor(x, dtype=torch.float64)


def _state(pos, euler=(0.0, 0.0, 0.0), v=(0.0, 0.0, 0.0), w=(0.0, 0.0, 0.0)):
    q = euler_to_quat(*(_t(a) for a in euler))
    return torch.cat([_t(pos), q, _t(v), _t(w)]).unsqueeze(0)


def _lowest_corner_at(sim, euler, height):
    """Centre z such that the lowest corner of the cube (orientation ``euler``) is at ``height``."""
    R = rotation_matrix(euler_to_quat(*(_t(a) for a in euler)).unsqueeze(0))[0]
    return sim.side / 2 * R[2].abs().sum().item() + height


def _energy(sim: CubeSimulator, params: torch.Tensor, S: torch.Tensor) -> np.ndarray:
    """Kinetic + gravitational + elastic energy of states S (T, 13); the elastic potential of
    f_k = k δ sp(d/δ) is U(d) = −k δ² Li₂(−e^{d/δ}) (Li₂(z) = spence(1 − z))."""
    c = sim._consts(params[:1])
    k, d = c.k[0, 0].item(), sim.contact_width
    r = (quat_outer(S[:, 3:7]) @ c.corner_form).unflatten(-1, (8, 3))
    x = (-(S[:, 2:3] + r[..., 2]) / d).numpy()
    U = np.where(x < -30, 0.0, -k * d * d * spence(1 + np.exp(np.minimum(x, 600))))
    kinetic = 0.5 * sim.mass * (S[:, 7:10] ** 2).sum(-1) + 0.5 * sim.inertia * (S[:, 10:13] ** 2).sum(-1)
    return kinetic.numpy() + sim.mass * G * S[:, 2].numpy() + U.sum(-1)


@pytest.mark.parametrize("log10_kn,side,mass", [(6.0, 0.2, 1.0), (5.5, 0.2, 1.0), (6.5, 0.1048, 0.37)])
def test_rest_penetration(log10_kn, side, mass):
    """A cube resting on a face settles where 4 corners carry m g: k δ sp(d/δ) = m g / 4."""
    sim = get_simulator("cube") if (side, mass) == (0.2, 1.0) else CubeSimulator(side=side, mass=mass)
    p = sim.default_params(1)
    p[0, 0] = log10_kn
    k = 10**log10_kn
    S = sim.rollout(p, sim.default_state(1), None, 100)
    depth = side / 2 - S[0, -1, 2].item()
    assert depth == pytest.approx(rest_penetration(mass, k, 4), rel=1e-6)
    # the same balance solved here, independently of the module's Newton iteration: φ(k δ sp(d/δ)) = m g / 4
    from scipy.optimize import brentq

    from risp_tasks.sims.cube import CONTACT_WIDTH as delta, FLOOR_WIDTH as w

    def excess(d):
        f = k * delta * np.logaddexp(0.0, d / delta)
        return f / (1.0 + np.exp(-f / w)) - mass * G / 4

    assert depth == pytest.approx(brentq(excess, -50 * delta, 0.01, xtol=1e-15, rtol=1e-12), rel=1e-6)
    if mass * G / (4 * k) > 2 * sim.contact_width:  # well past the smoothing: the penalty law m g / (n k_n)
        assert depth == pytest.approx(mass * G / (4 * k), rel=0.05)
    assert S[0, -1, 7:].abs().max() < 1e-9


def test_free_flight_is_ballistic():
    sim = CubeSimulator(substeps=3)
    s0 = _state((0.0, 0.0, 2.0), (0.3, 0.2, 0.1), v=(0.5, 0.0, 1.0), w=(1.0, -2.0, 3.0))
    S = sim.rollout(sim.default_params(1), s0, None, 30)
    h = sim.dt / 3
    N = torch.arange(31, dtype=torch.float64) * 3
    expected_z = 2.0 + 1.0 * N * h - G * h * h * N * (N + 1) / 2  # semi-implicit Euler, exactly
    assert torch.allclose(S[0, :, 2], expected_z, atol=1e-12)
    assert torch.allclose(S[0, :, 0], 0.5 * N * h, atol=1e-12)
    # isotropic inertia: the world-frame angular velocity is constant
    w_world = (rotation_matrix(S[0, :, 3:7]) @ S[0, :, 10:13].unsqueeze(-1)).squeeze(-1)
    assert torch.allclose(w_world, w_world[0].expand_as(w_world), atol=1e-12)


def _bounce(dn: float, alpha: float | None = None, steps: int = 100):
    """A flat cube (spinning about z) hitting the floor at 1 m/s, resolved with h = 10 µs."""
    effects = ("restitution",) if alpha is not None else ()
    sim = CubeSimulator(effects, dt=1e-4, substeps=10)
    p = sim.default_params(1)
    p[0, 0], p[0, 1] = 5.5, dn
    if alpha is not None:
        p[0, 2] = alpha
    s0 = _state((0.0, 0.0, sim.side / 2 + 5e-4), v=(0.0, 0.0, -1.0), w=(0.0, 0.0, 2.0))
    with torch.no_grad():
        S = sim.rollout(p, s0, None, steps)[0]
    return sim, p, S


def test_bounce_conserves_energy_without_damping_and_loses_it_with():
    losses = []
    for dn in (0.0, 50.0, 100.0):
        sim, p, S = _bounce(dn)
        assert S[-1, 9] > 0 and S[-1, 2] > sim.side / 2  # it bounced and is back in the air
        E = _energy(sim, p, S)
        losses.append((E[0] - E[-1]) / E[0])
    assert abs(losses[0]) < 0.02  # no damping: conserved over the bounce up to the numerical loss ≈ ω h
    assert losses[0] < losses[1] < losses[2]  # energy goes only where the modelled damping takes it
    assert losses[2] > 0.05


@pytest.mark.parametrize("effects", [(), tuple(EFFECTS)])
def test_energy_non_increasing_between_contacts(effects):
    """Dropped from 5 cm with tilt and spin, default (unresolved, implicit) integrator: the energy of the
    samples out of contact never increases, and the cube comes to rest with less energy than it started.
    (Within an unresolved impact the discrete energy is not monotone: docs §3.4.)"""
    sim = get_simulator("cube", effects)
    euler = (0.0, 0.3, 0.2)
    s0 = _state((0.0, 0.0, _lowest_corner_at(sim, euler, 0.05)), euler, v=(0.2, 0.0, 0.0), w=(0.0, 3.0, 0.0))
    p = sim.default_params(1)
    with torch.no_grad():
        S = sim.rollout(p, s0, None, 100)[0]
    c = sim._consts(p)
    r = (quat_outer(S[:, 3:7]) @ c.corner_form).unflatten(-1, (8, 3))
    free = ((S[:, 2:3] + r[..., 2]) > 1e-4).all(-1).numpy()  # no corner within 0.1 mm of the floor
    E = _energy(sim, p, S)
    assert free.sum() >= 5 and not free[-1]
    assert (np.diff(E[free]) <= 1e-9 * E[0]).all()
    assert E[-1] < E[0]
    assert abs(S[-1, 9]) < 1e-3  # settled on a face (without friction it may still slide and spin)
    if "friction" in effects:
        assert S[-1, 7:].abs().max() < 1e-3


def test_hunt_crossley_restitution():
    """e² ≈ 1 − (4/3)·α·v_in for the restitution effect (docs §3.3), relative to the undamped bounce."""
    _, _, S0 = _bounce(0.0, alpha=0.0)
    _, _, S1 = _bounce(0.0, alpha=0.1)
    e = S1[-1, 9].item() / S0[-1, 9].item()
    assert e == pytest.approx(math.sqrt(1 - 4 / 3 * 0.1 * 1.0), rel=0.015)


@pytest.mark.parametrize("substeps, rel", [(2, 0.03), (50, 0.01)])
def test_sliding_friction_decelerates_at_mu_g(substeps, rel):
    """A block sliding on a face: Coulomb's v(t) = v₀ − μgt as h → 0. The lagged implicit damper (docs §3.4)
    gives about v' = v / (1 + hμg/v) per substep: a little less deceleration than μg, never more."""
    sim = get_simulator("cube", ("friction",), substeps=substeps)
    p = sim.default_params(1)
    p[0, 2] = 0.3
    z = sim.side / 2 - rest_penetration(sim.mass, 1e6, 4)
    S = sim.rollout(p, _state((0.0, 0.0, z), v=(1.0, 0.0, 0.0)), None, 20)
    deceleration = (1.0 - S[0, -1, 7].item()) / 0.2
    assert deceleration == pytest.approx(0.3 * G, rel=rel)
    assert deceleration < 0.3 * G
    assert (S[0, 1:, 7] < S[0, :-1, 7]).all()
    assert abs(S[0, -1, 8].item()) < 1e-9


def _energy_gain_of_tosses(opts, mu_range, mu_r_high=0.0, B=12, steps=150):
    """max_t E(t) / E(0) of B seeded tosses (fast spin) with friction μ uniform in mu_range; E is kinetic +
    gravitational, not :func:`_energy`: with its elastic term the total rises by up to 2.9 % inside the
    unresolved impacts of these tosses at μ ≤ 0.3 (docs §3.4: not monotone within an impact), where kinetic +
    gravitational energy never rises."""
    effects = ("friction", "rolling_friction") if mu_r_high > 0 else ("friction",)
    sim = get_simulator("cube", effects, **opts)
    rng = np.random.default_rng(0)
    s0 = torch.zeros(B, 13, dtype=torch.float64)
    s0[:, 2] = torch.tensor(rng.uniform(0.15, 0.4, B))
    s0[:, 3:7] = torch.stack([euler_to_quat(*torch.tensor(rng.uniform(-3, 3, 3)).unbind()) for _ in range(B)])
    s0[:, 7:10] = torch.tensor(rng.uniform(-2, 2, (B, 3)))
    s0[:, 10:13] = torch.tensor(rng.uniform(-10, 10, (B, 3)))
    p = sim.default_params(B).clone()
    p[:, sim.param_index("friction.mu")] = torch.tensor(rng.uniform(*mu_range, B))
    if mu_r_high > 0:
        p[:, sim.param_index("rolling_friction.mu_r")] = torch.tensor(rng.uniform(0.0, mu_r_high, B))
    with torch.no_grad():
        S = sim.rollout(p, s0, None, steps)
    assert torch.isfinite(S).all()
    E = (0.5 * sim.mass * S[..., 7:10].pow(2).sum(-1) + 0.5 * sim.inertia * S[..., 10:13].pow(2).sum(-1)
         + sim.mass * G * S[..., 2])
    return E.max(1).values / E[:, 0]


CUBES = [{}, {"side": 0.1048, "mass": 0.37}, {"side": 0.1048, "mass": 0.37, "dt": 1 / 148}]


@pytest.mark.parametrize("opts", CUBES)
def test_friction_up_to_0_3_feeds_no_energy_into_a_toss(opts):
    """Fast-spinning tosses (2 m/s, 10 rad/s) with μ ≤ 0.3 (the real tosses fit μ ≈ 0.22): the total energy
    never rises above its start."""
    gain = _energy_gain_of_tosses(opts, (0.0, 0.3), mu_r_high=0.01)
    assert (gain <= 1 + 1e-6).all(), gain


@pytest.mark.parametrize("opts", [{"substeps": 4}] + CUBES[1:])
def test_friction_never_feeds_energy_into_a_toss(opts):
    """The same at μ ∈ [0.5, 1), inside the effect's plausible range: it must not gain energy either (before
    the lagged implicit damper of docs §3.4 these tosses gained up to 1500×)."""
    gain = _energy_gain_of_tosses(opts, (0.5, 1.0))
    assert (gain <= 1 + 1e-6).all(), gain


@pytest.mark.xfail(strict=True, reason="known limitation (docs/models.md §3.4): at 5 ms substeps a face of the "
                   "0.2 m cube can land flat within one substep; its corners were out of contact at the substep's "
                   "start, the solve does not see them, and the 2 cm penetration pops the cube up")
def test_default_cube_at_5_ms_substeps_keeps_its_energy_at_high_friction():
    gain = _energy_gain_of_tosses({}, (0.5, 1.0))
    assert (gain <= 1 + 1e-6).all(), gain


def test_rolling_friction_decelerates_spin():
    sim = get_simulator("cube", ("rolling_friction",))
    p = sim.default_params(1)
    mu_r = p[0, 2].item()
    z = sim.side / 2 - rest_penetration(sim.mass, 1e6, 4)
    S = sim.rollout(p, _state((0.0, 0.0, z), w=(0.0, 0.0, 5.0)), None, 50)
    expected = 5.0 - mu_r * sim.mass * G / sim.inertia * 0.5
    assert S[0, -1, 12].item() == pytest.approx(expected, rel=0.01)


def test_rollout_equals_repeated_step():
    sim = get_simulator("cube", tuple(EFFECTS))
    euler = (0.2, 0.15, 0.1)
    s0 = _state((0.0, 0.0, _lowest_corner_at(sim, euler, 0.002)), euler, v=(0.3, 0.0, -0.5), w=(1.0, -2.0, 3.0))
    p = sim.default_params(1)
    S = sim.rollout(p, s0, None, 4)
    s = s0
    for t in range(4):
        s = sim.step(p, s, None, t)
        assert torch.allclose(S[:, t + 1], s, atol=1e-12)


def _contact_case(sim):
    euler = (0.2, 0.15, 0.1)
    z = _lowest_corner_at(sim, euler, -3e-6)  # one corner 3 µm into the floor
    return _state((0.0, 0.0, z), euler, v=(0.3, -0.2, -0.4), w=(1.0, -2.0, 3.0))


@pytest.mark.parametrize("effects", [()] + [(e,) for e in EFFECTS])
def test_gradcheck_in_contact(effects):
    # eps = 1e-8: the contact law varies on the scale δ = 1 µm, so larger central-difference steps
    # are themselves inaccurate (their error falls 100× per 10× smaller step, until rounding wins).
    sim = get_simulator("cube", effects)
    p = sim.default_params(1).requires_grad_()
    s0 = _contact_case(sim).requires_grad_()
    assert gradcheck(lambda p_, s_: sim.rollout(p_, s_, None, 3), (p, s0), eps=1e-8, atol=1e-4, rtol=1e-3)


def test_effect_parameters_change_the_trajectory():
    for effect in EFFECTS:
        sim = get_simulator("cube", (effect,))
        p = sim.default_params(1).requires_grad_()
        S = sim.rollout(p, _contact_case(sim), None, 3)
        (g,) = torch.autograd.grad(S[:, -1].pow(2).sum(), p)
        assert g[0, -1] != 0, effect


def test_float32_matches_float64():
    sim = get_simulator("cube", ("friction",))
    s0 = _contact_case(sim)
    S64 = sim.rollout(sim.default_params(1), s0, None, 30)
    S32 = sim.rollout(sim.default_params(1, torch.float32), s0.float(), None, 30)
    assert S32.dtype == torch.float32
    assert torch.allclose(S32.double(), S64, atol=2e-3)


@pytest.mark.parametrize("column,value,word", [(0, 1.0, "log10_kn"), (0, 10.0, "log10_kn"), (1, -1.0, "dn"),
                                               (2, -0.1, "friction.mu"), (2, float("nan"), "friction.mu")])
def test_bad_params(column, value, word):
    sim = get_simulator("cube", ("friction",))
    p = sim.default_params(1)
    p[0, column] = value
    with pytest.raises(RispError, match=word):
        sim.rollout(p, sim.default_state(1), None, 2)


def test_bad_inputs_and_options():
    sim = get_simulator("cube")
    p, s0 = sim.default_params(1), sim.default_state(1)
    with pytest.raises(RispError, match="actions"):
        sim.rollout(p, s0, torch.zeros(1, 2, 1, dtype=torch.float64), 2)
    with pytest.raises(RispError, match="s0"):
        sim.rollout(p, s0[:, :7], None, 2)
    s_nan = s0.clone()
    s_nan[0, 2] = float("nan")
    with pytest.raises(RispError, match="s0"):
        sim.rollout(p, s_nan, None, 2)
    with pytest.raises(RispError, match="params"):
        sim.rollout(p[:, :1], s0, None, 2)
    with pytest.raises(RispError, match="quaternion"):
        sim.rollout(p, torch.zeros_like(s0), None, 2)
    for option in ({"side": 0.0}, {"mass": -1.0}, {"dt": float("nan")}, {"substeps": 0}, {"contact_width": 0.0}):
        with pytest.raises(RispError, match=next(iter(option))):
            CubeSimulator(**option)
