"""Hand simulator (docs/models/hand.md): dynamics against an independent Lagrangian, gradients against
finite differences, the physics checks of issue 3, and clear errors for bad input."""

from __future__ import annotations

import math

import pytest
import torch

from risp_data.envs import hand as geometry
from risp_data.errors import RispError
from risp_tasks.sims import get_simulator
from risp_tasks.sims.hand import (
    DT,
    LINEAR_DENSITY,
    N_JOINTS,
    hand_torque_schedule,
)

ALL_EFFECTS = ("joint_damping", "joint_friction", "gravity")


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _random_state(gen, batch, dtype=torch.float64, angle=0.6, rate=2.0):
    q = angle * (2 * torch.rand(batch, N_JOINTS, generator=gen, dtype=dtype) - 1)
    v = rate * (2 * torch.rand(batch, N_JOINTS, generator=gen, dtype=dtype) - 1)
    return torch.cat((q, v), -1)


def test_layout_and_registry():
    sim = get_simulator("hand", ("joint_damping", "joint_friction"))
    assert sim.param_names == tuple(f"stiffness_{f}" for f in geometry.FINGERS) + (
        "joint_damping.coefficient", "joint_friction.torque")
    assert len(sim.state_names) == 26 and sim.action_dim == 5 and sim.dt == DT
    assert sim.default_params(3).shape == (3, 7)
    states = torch.randn(4, 7, 26, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert torch.equal(sim.to_env_state(states), states[..., :13])
    # the shared interface: bounds, ranges, units, default_state (rest_state is its alias)
    assert sim.param_bounds == ((0.0, math.inf),) * 7
    assert sim.spec.base_param_ranges == ((0.0, 1.0),) * 5 and len(sim.spec.base_param_units) == 5
    assert all(e.bounds and e.units for e in sim.spec.available_effects.values())
    assert torch.equal(sim.default_state(2), torch.zeros(2, 26, dtype=torch.float64))
    assert torch.equal(sim.rest_state(2), sim.default_state(2))


# -- the planar-chain dynamics against an independent 3-D Lagrangian ---------------------------------------
def _rot_x(theta):
    c, s = torch.cos(theta), torch.sin(theta)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    return torch.stack((torch.stack((one, zero, zero)), torch.stack((zero, c, -s)), torch.stack((zero, s, c))))


def _kinetic_energy(f, q, v):
    """½ Σ m |ṗ_c|² + ½ Σ ωᵀ I_world ω for finger f, from 3-D forward kinematics (world frame)."""
    d = torch.tensor(geometry.FINGER_DIRECTIONS[f], dtype=torch.float64)
    d = d / d.norm()
    r = geometry.LINK_RADIUS

    def com_positions(q):
        p, out, phi = torch.zeros(3, dtype=torch.float64), [], torch.zeros((), dtype=torch.float64)
        for k, L in enumerate(geometry.LINK_LENGTHS[f]):
            phi = phi + q[k]
            u = _rot_x(phi) @ d
            out.append(p + 0.5 * L * u)
            p = p + L * u
        return torch.stack(out)

    jac = torch.autograd.functional.jacobian(com_positions, q, create_graph=True)  # (links, 3, joints)
    T = torch.zeros((), dtype=torch.float64)
    phi = torch.zeros((), dtype=torch.float64)
    omega = torch.zeros((), dtype=torch.float64)
    for k, L in enumerate(geometry.LINK_LENGTHS[f]):
        m = LINEAR_DENSITY * L
        phi, omega = phi + q[k], omega + v[k]
        u = _rot_x(phi) @ d
        inertia = m * (3 * r * r + L * L) / 12 * torch.eye(3, dtype=torch.float64) \
            + (m * r * r / 2 - m * (3 * r * r + L * L) / 12) * torch.outer(u, u)
        w = omega * torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        vel = jac[k] @ v
        T = T + 0.5 * m * vel @ vel + 0.5 * w @ inertia @ w
    return T


def test_mass_matrix_and_coriolis_match_lagrangian():
    sim = get_simulator("hand")
    c = sim._consts(torch.float64)
    gen = torch.Generator().manual_seed(1)
    state = _random_state(gen, 1, angle=0.8, rate=3.0)
    q13, v13 = state[:, :13], state[:, 13:]
    M, h, _ = sim._inertial_terms(sim._pad(q13, c), sim._pad(v13, c), c)
    start = 0
    for f, n in enumerate(geometry.JOINTS_PER_FINGER):
        q = q13[0, start:start + n].clone().requires_grad_()
        v = v13[0, start:start + n].clone().requires_grad_()
        T = _kinetic_energy(f, q, v)
        dT_dv, dT_dq = torch.autograd.grad(T, (v, q), create_graph=True)
        M_ref = torch.stack([torch.autograd.grad(dT_dv[k], v, retain_graph=True)[0] for k in range(n)])
        # h = d/dt(∂T/∂q̇)|_{q̈=0} − ∂T/∂q = (∂²T/∂q̇∂q) q̇ − ∂T/∂q
        mixed = torch.stack([torch.autograd.grad(dT_dv[k], q, retain_graph=True)[0] for k in range(n)])
        h_ref = mixed @ v.detach() - dT_dq.detach()
        torch.testing.assert_close(M[0, f, :n, :n], M_ref.detach(), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(h[0, f, :n], h_ref, rtol=1e-9, atol=1e-12)
        start += n


# -- gradients ----------------------------------------------------------------------------------------
def test_gradcheck_params_actions_state_all_effects():
    sim = get_simulator("hand", ALL_EFFECTS)
    gen = torch.Generator().manual_seed(2)
    params = torch.tensor([[0.3, 0.9, 0.5, 0.7, 0.1, 0.08, 0.03, 4.0]], dtype=torch.float64)
    s0 = _random_state(gen, 1, angle=0.9)  # some joints start beyond ±π/4: the barrier is active
    actions = 2 * torch.rand(1, 3, 5, generator=gen, dtype=torch.float64) - 1

    def f(p, s, a):
        return sim.rollout(p, s, a, 3)

    assert torch.autograd.gradcheck(f, (params.requires_grad_(), s0.requires_grad_(), actions.requires_grad_()))


def test_torque_schedule_formula_and_gradients():
    m = torch.tensor([[1.0, 0.5, 0.0, 0.8, 0.3]], dtype=torch.float64)
    delta = torch.tensor([[0.0, 10.0, 20.0, 33.5, 40.0]], dtype=torch.float64)
    steps = 90
    t = torch.arange(steps, dtype=torch.float64)
    hard = m[:, None] * torch.sin(2 * math.pi * ((t[None, :, None] - delta[:, None]) / 40).clamp(0, 1))
    torch.testing.assert_close(hand_torque_schedule(m, delta, steps), hard)  # default: the exact formula
    torch.testing.assert_close(hand_torque_schedule(m, delta, steps, smoothing=0.0), hard)
    smooth = hand_torque_schedule(m, delta, steps, smoothing=1.0)  # opt-in smoothing for optimisation
    assert (smooth - hard).abs().max() < 0.15  # within a step of the corners
    far = ((t[None, :, None] - delta[:, None]).abs() > 6) & ((t[None, :, None] - delta[:, None] - 40).abs() > 6)
    assert (smooth - hard)[far].abs().max() < 1e-3
    gen = torch.Generator().manual_seed(12)
    m_ = (0.2 + 0.6 * torch.rand(2, 5, generator=gen, dtype=torch.float64)).requires_grad_()
    d_ = (1 + 38 * torch.rand(2, 5, generator=gen, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: hand_torque_schedule(a, b, 60, smoothing=1.0), (m_, d_))
    assert torch.autograd.gradcheck(lambda a, b: hand_torque_schedule(a, b, 60), (m_, d_))
    # the smooth clamp keeps δ's gradient alive on the step just before the ramp starts
    d = torch.tensor([[10.0] * 5], dtype=torch.float64, requires_grad=True)
    hand_torque_schedule(torch.ones(1, 5, dtype=torch.float64), d, 11, smoothing=1.0)[0, 9].sum().backward()
    assert (d.grad.abs() > 1e-3).all()


# -- physics ---------------------------------------------------------------------------------------------
def test_zero_action_returns_to_rest_pose():
    sim = get_simulator("hand")
    gen = torch.Generator().manual_seed(3)
    s0 = _random_state(gen, 4)
    states = sim.rollout(sim.default_params(4), s0, torch.zeros(4, 600, 5, dtype=torch.float64), 600)
    assert states[:, -1].abs().max() < 1e-3
    assert states[:, 0, :13].abs().max() > 0.3  # it really started away from rest


def test_joint_limits_hold_under_full_torque():
    sim = get_simulator("hand")
    params = torch.zeros(1, 5, dtype=torch.float64)  # no spring: only the limit stops the fingers
    states = sim.rollout(params, sim.rest_state(1), torch.ones(1, 150, 5, dtype=torch.float64), 150)
    q = states[0, :, :13]
    # the softplus barrier already pushes 0.01–0.02 rad before the limit; at ≈18 rad/s the
    # distal joints overshoot it by less than 0.01 rad
    assert q.max() < geometry.JOINT_LIMIT + 0.02
    assert (q[-1] > geometry.JOINT_LIMIT - 0.03).all()  # pressed against the limit, not short of it
    back = sim.rollout(params, sim.rest_state(1), -torch.ones(1, 150, 5, dtype=torch.float64), 150)
    assert back[0, :, :13].min() > -geometry.JOINT_LIMIT - 0.02


def test_static_deflection_equals_torque_over_stiffness():
    """Spring equilibrium k q = u at every joint (torque applied to each joint of the finger)."""
    sim = get_simulator("hand")
    params = torch.tensor([[0.5, 1.0, 0.8, 2.0, 4.0]], dtype=torch.float64)
    u = torch.tensor([0.2, 0.3, 0.4, 0.5, 0.6], dtype=torch.float64)
    states = sim.rollout(params, sim.rest_state(1), u.expand(1, 800, 5), 800)
    expected = (u / params[0])[sim._consts(torch.float64)["finger_of_joint"]]
    torch.testing.assert_close(states[0, -1, :13], expected, rtol=1e-4, atol=1e-5)


def _mechanical_energy(sim, params, states):
    """½ q̇ᵀ M(q) q̇ + ½ Σ k q² per state (barrier not included: keep away from the limits)."""
    c = sim._consts(states.dtype)
    q, v = states[..., :13].reshape(-1, 13), states[..., 13:].reshape(-1, 13)
    M, _, _ = sim._inertial_terms(sim._pad(q, c), sim._pad(v, c), c)
    vp = sim._pad(v, c)
    kinetic = 0.5 * torch.einsum("bfj,bfjk,bfk->b", vp, M, vp)
    k = params[0, :5][c["finger_of_joint"]]
    return (kinetic + 0.5 * (k * q * q).sum(-1)).reshape(states.shape[:-1])


def test_energy_decays_and_effects_dissipate_more():
    gen = torch.Generator().manual_seed(4)
    s0 = _random_state(gen, 1, angle=0.4, rate=1.0)
    zero = torch.zeros(1, 60, 5, dtype=torch.float64)
    base_sim = get_simulator("hand")
    base_params = torch.ones(1, 5, dtype=torch.float64)
    base = base_sim.rollout(base_params, s0, zero, 60)
    assert base[0, :, :13].abs().max() < geometry.JOINT_LIMIT - 0.1
    energy = _mechanical_energy(base_sim, base_params, base)[0]
    assert (energy[1:] <= energy[:-1] * (1 + 1e-9)).all()  # dissipative: base damping + implicit Euler
    assert energy[-1] < 0.5 * energy[0]
    # implicit Euler damps the stiff distal modes numerically (docs/models/hand.md, "Integrator"), and
    # an overdamped joint keeps its spring energy longer: compare one step from a spring-free state
    moving = s0.clone()
    moving[:, :13] = 0.0
    one = _mechanical_energy(base_sim, base_params, base_sim.rollout(base_params, moving, zero, 1))[0]
    for effect, value in (("joint_damping", 0.3), ("joint_friction", 0.05)):
        sim = get_simulator("hand", (effect,))
        params = torch.cat((base_params, torch.tensor([[value]], dtype=torch.float64)), -1)
        damped = _mechanical_energy(base_sim, base_params, sim.rollout(params, moving, zero, 1))[0]
        assert damped[1] < one[1] - 0.05 * (one[0] - one[1])
        longer = _mechanical_energy(base_sim, base_params, sim.rollout(params, s0, zero, 60))[0]
        assert (longer[1:] <= longer[:-1] * (1 + 1e-9)).all()
    sim = get_simulator("hand", ("gravity",))
    params = torch.tensor([[0.0] * 5 + [9.81]], dtype=torch.float64)
    s = torch.zeros(1, 26, dtype=torch.float64)
    s[0, 2] = 0.1  # index finger slightly bent: gravity bends it further (fingers point up)
    fallen = sim.rollout(params, s, zero, 20)
    assert fallen[0, -1, 2] > 0.15


def test_batch_and_float32_agree():
    sim = get_simulator("hand", ("joint_friction",))
    gen = torch.Generator().manual_seed(5)
    s0 = _random_state(gen, 3)
    params = torch.rand(3, 6, generator=gen, dtype=torch.float64) * 0.9
    params[:, 5] *= 0.1 / 0.9  # friction torque within its documented range [0, 0.1] N·m
    a = hand_torque_schedule(torch.rand(3, 5, generator=gen, dtype=torch.float64),
                             40 * torch.rand(3, 5, generator=gen, dtype=torch.float64), 50)
    together = sim.rollout(params, s0, a, 50)
    for b in range(3):
        torch.testing.assert_close(sim.rollout(params[b:b + 1], s0[b:b + 1], a[b:b + 1], 50)[0], together[b])
    single = sim.rollout(params.float(), s0.float(), a.float(), 50)
    assert single.dtype == torch.float32
    assert (single.double() - together)[..., :13].abs().max() < 1e-3


# -- bad input -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case, fragment", [
    ("params_shape", "params"), ("params_nan", "stiffness_index"), ("negative", "stiffness_ring"),
    ("s0_shape", "s0"), ("actions_shape", "actions"), ("actions_nan", "actions"), ("dtype", "dtype"),
])
def test_bad_rollout_input_names_the_argument(case, fragment):
    sim = get_simulator("hand")
    p, s0, a = sim.default_params(2), sim.rest_state(2), torch.zeros(2, 5, 5, dtype=torch.float64)
    if case == "params_shape":
        p = p[:, :4]
    elif case == "params_nan":
        p[1, 1] = float("nan")
    elif case == "negative":
        p[0, 3] = -0.1
    elif case == "s0_shape":
        s0 = s0[:, :13]
    elif case == "actions_shape":
        a = a[:, :, :3]
    elif case == "actions_nan":
        a[0, 2, 1] = float("inf")
    elif case == "dtype":
        a = a.float()
    with pytest.raises(RispError, match=fragment):
        sim.rollout(p, s0, a, 5)


def test_bad_schedule_and_effect_input():
    ok = torch.full((1, 5), 0.5, dtype=torch.float64)
    with pytest.raises(RispError, match="m must"):
        hand_torque_schedule(ok * 3, ok, 10)
    with pytest.raises(RispError, match="delta must"):
        hand_torque_schedule(ok, ok * 100, 10)
    with pytest.raises(RispError, match="delta"):
        hand_torque_schedule(ok, ok[:, :4], 10)
    with pytest.raises(RispError, match="unknown effect"):
        get_simulator("hand", ("rolling_friction",))
    with pytest.raises(RispError, match="states"):
        get_simulator("hand").to_env_state(torch.zeros(3, 13))
