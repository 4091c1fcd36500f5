"""Quadrotor simulator: physics checks against closed forms (docs/models.md §2) and gradient checks."""

from __future__ import annotations

import math

import pytest
import torch
from torch.autograd import gradcheck

from risp_data.envs.quadrotor import ARM_LENGTH, ROTOR_HEIGHT, ROTOR_RADIUS
from risp_data.envs.rotations import euler_to_quat
from risp_data.errors import RispError
from risp_tasks.sims import get_simulator
from risp_tasks.sims.quadrotor import (
    COMMAND_LIMIT,
    DT,
    EFFECTS,
    GROUND_Z_MIN,
    GROUND_Z_WIDTH,
    K_F,
    K_M,
    MASS,
    QuadrotorSimulator,
    default_inertia,
    hover_command,
)

G = 9.81
ALL_EFFECTS = tuple(EFFECTS)



pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _t(x):
    return torch.tensor(x, dtype=torch.float64)


def _moving_state(sim, batch=2):
    """A state with every component non-trivial (tilted, moving, spinning, low enough for ground effect)."""
    s0 = sim.default_state(batch)
    s0[:, 2] = 0.3
    s0[:, 3:7] = euler_to_quat(_t(0.2), _t(0.1), _t(-0.1))
    s0[:, 7:13] = _t([0.5, -0.3, 0.2, 0.3, -0.2, 0.5])
    return s0


def test_hover_command_value():
    assert hover_command(MASS) == pytest.approx(MASS * G / (4 * K_F))
    assert hover_command(MASS) == pytest.approx(147.15)


def test_default_inertia_from_geometry():
    Ixx, Iyy, Izz = default_inertia(3.0)
    # box of 1.8 kg (half extents 0.08, 0.08, 0.04) + 4 motors of 0.3 kg at 0.3 m
    assert Ixx == pytest.approx(1.8 / 3 * (0.08**2 + 0.04**2) + 2 * 0.3 * 0.09)
    assert Izz == pytest.approx(1.8 / 3 * (2 * 0.08**2) + 4 * 0.3 * 0.09)
    assert Ixx == Iyy


def test_free_fall_matches_g_t2_over_2():
    sim = get_simulator("quadrotor")
    p = sim.default_params(1)
    steps = 100
    S = sim.rollout(p, sim.default_state(1), torch.zeros(1, steps, 4, dtype=torch.float64), steps)
    n = torch.arange(steps + 1, dtype=torch.float64)
    t = n * DT
    drop = 1.0 - S[0, :, 2]
    # semi-implicit Euler: exactly g h² n(n+1)/2, i.e. g t²/2 plus the O(h) term g h t / 2
    assert torch.allclose(drop, G * DT**2 * n * (n + 1) / 2, atol=1e-12)
    assert drop[-1].item() == pytest.approx(G * t[-1].item() ** 2 / 2, rel=1.5 * DT / t[-1].item())
    assert torch.allclose(S[0, :, :2], torch.zeros(steps + 1, 2, dtype=torch.float64))
    assert torch.allclose(S[0, :, 3:7], _t([1.0, 0, 0, 0]).expand(steps + 1, 4))


@pytest.mark.parametrize("effects", [(), ("motor_lag",), ("rotor_drag", "air_drag", "motor_lag")])
def test_hover_stays_put(effects):
    sim = get_simulator("quadrotor", effects)
    p = sim.default_params(2)
    p[1, 0] = 2.9  # a lighter quadrotor hovers at its own u_h
    if "motor_lag" in effects:
        s0 = sim.default_state(2)
        s0[:, 13:17] = (p[:, 0:1] * G / 4).expand(-1, 4)
    else:
        s0 = sim.default_state(2)
    a = sim.hover_actions(p, 200)
    assert a[1, 0, 0].item() == pytest.approx(2.9 * G / (4 * K_F))
    S = sim.rollout(p, s0, a, 200)
    assert (S[:, :, :3] - s0[:, None, :3]).abs().max() < 1e-9
    assert (S[:, :, 7:13]).abs().max() < 1e-9


def test_rotor_mixing_and_yaw_torque():
    """One step from rest: ω̇ = I⁻¹ (L(f1 − f3), L(f2 − f0), k_m Σ s_i f_i), f_i = k_f u_i."""
    sim = get_simulator("quadrotor")
    p = sim.default_params(1)
    u = _t([[100.0, 140.0, 120.0, 90.0]])
    S = sim.rollout(p, sim.default_state(1), u[:, None], 1)
    f = K_F * u[0]
    Ixx, Iyy, Izz = default_inertia(MASS)
    expected = torch.stack([ARM_LENGTH * (f[1] - f[3]) / Ixx, ARM_LENGTH * (f[2] - f[0]) / Iyy,
                            K_M * (f[0] - f[1] + f[2] - f[3]) / Izz]) * DT
    assert torch.allclose(S[0, 1, 10:13], expected, rtol=1e-12)
    assert S[0, 1, 9].item() == pytest.approx((f.sum().item() / MASS - G) * DT, rel=1e-12)


def test_commands_are_smoothly_clamped():
    sim = get_simulator("quadrotor")
    p = sim.default_params(1).requires_grad_()
    u = _t([[[1e4, 600.0, -1e4, 400.0]]]).requires_grad_()
    thrust = sim._commanded_thrust(p, u)[0, 0]
    assert thrust[0].item() == pytest.approx(K_F * COMMAND_LIMIT, rel=1e-9)
    assert K_F * 495 < thrust[1].item() < K_F * COMMAND_LIMIT
    assert thrust[2].item() == pytest.approx(-K_F * COMMAND_LIMIT, rel=1e-9)
    assert thrust[3].item() == pytest.approx(K_F * 400.0, rel=1e-6)
    thrust.sum().backward()
    assert (u.grad[0, 0, 1] > 0) and (u.grad[0, 0, 3] > 0.99 * K_F)


def test_motor_lag_is_first_order():
    sim = get_simulator("quadrotor", ("motor_lag",))
    p = sim.default_params(1)
    tau = p[0, sim.param_index("motor_lag.tau")].item()
    s0 = sim.default_state(1)
    s0[:, 13:] = 0.0
    S = sim.rollout(p, s0, torch.full((1, 20, 4), 200.0, dtype=torch.float64), 20)
    n = torch.arange(21, dtype=torch.float64)
    expected = K_F * 200.0 * (1 - torch.exp(-n * DT / tau))
    assert torch.allclose(S[0, :, 13], expected, rtol=1e-10, atol=1e-12)
    assert sim.state_names[13:] == ("f0", "f1", "f2", "f3")


def test_ground_effect_formula():
    sim = get_simulator("quadrotor", ("ground_effect",))
    p = sim.default_params(1)
    k = p[0, -1].item()
    z = 0.2
    s0 = sim.default_state(1)
    s0[:, 2] = z
    S = sim.rollout(p, s0, sim.hover_actions(p, 1), 1)
    zr = z + ROTOR_HEIGHT
    z_hat = GROUND_Z_MIN + GROUND_Z_WIDTH * math.log1p(math.exp((zr - GROUND_Z_MIN) / GROUND_Z_WIDTH))
    factor = 1 + k * (ROTOR_RADIUS / (4 * z_hat)) ** 2
    assert S[0, 1, 9].item() == pytest.approx(G * (factor - 1) * DT, rel=1e-9)


def test_drag_and_wind_forces():
    sim = get_simulator("quadrotor", ("rotor_drag", "air_drag", "wind"))
    p = sim.default_params(1)
    s0 = sim.default_state(1)
    v = _t([1.0, -2.0, 0.5])
    s0[:, 7:10] = v
    S = sim.rollout(p, s0, sim.hover_actions(p, 1), 1)
    D = p[0, 6:9]
    c = p[0, 9].item()
    wind = p[0, 10:13]
    force = -D * v - c * math.sqrt(v.dot(v).item() + 1e-6) * v + wind  # level: body frame = world frame
    assert torch.allclose(S[0, 1, 7:10], v + DT * force / MASS, rtol=1e-12)


def test_rollout_equals_repeated_step():
    sim = get_simulator("quadrotor", ALL_EFFECTS)
    p = sim.default_params(2)
    s0 = _moving_state(sim)
    a = sim.hover_actions(p, 5) + 10.0
    S = sim.rollout(p, s0, a, 5)
    s = s0
    for t in range(5):
        s = sim.step(p, s, a[:, t], t)
        assert torch.allclose(S[:, t + 1], s, atol=1e-14)


def test_gradcheck_params_actions_state():
    sim = get_simulator("quadrotor")
    p = sim.default_params(2).requires_grad_()
    s0 = _moving_state(sim).requires_grad_()
    gen = torch.Generator().manual_seed(0)
    a = (sim.hover_actions(p.detach(), 4) + 20 * torch.randn(2, 4, 4, dtype=torch.float64, generator=gen)).requires_grad_()
    assert gradcheck(lambda p_, s_, a_: sim.rollout(p_, s_, a_, 4), (p, s0, a))


@pytest.mark.parametrize("effect", ALL_EFFECTS)
def test_gradcheck_effect_params(effect):
    sim = get_simulator("quadrotor", (effect,))
    p = sim.default_params(2)
    p[1, len(sim.spec.base_param_names):] *= 1.3
    p.requires_grad_()
    s0 = _moving_state(sim).requires_grad_()
    a = (sim.hover_actions(p.detach(), 3) + 15.0).requires_grad_()
    assert gradcheck(lambda p_, s_, a_: sim.rollout(p_, s_, a_, 3), (p, s0, a))


def test_effect_parameters_change_the_trajectory():
    for effect in ALL_EFFECTS:
        sim = get_simulator("quadrotor", (effect,))
        p = sim.default_params(1).requires_grad_()
        S = sim.rollout(p, _moving_state(sim, 1), sim.hover_actions(p.detach(), 5) + 5.0, 5)
        (g,) = torch.autograd.grad(S[:, -1, :10].sum(), p)
        assert (g[0, len(sim.spec.base_param_names):] != 0).any(), effect


def test_to_env_state_round_trip():
    sim = get_simulator("quadrotor")
    s = sim.default_state(1)
    s[:, :3] = _t([0.1, -0.2, 0.8])
    s[:, 3:7] = euler_to_quat(_t(0.4), _t(-0.3), _t(0.2))
    env = sim.to_env_state(s)
    assert torch.allclose(env, _t([[0.1, -0.2, 0.8, 0.4, -0.3, 0.2]]), atol=1e-12)


@pytest.mark.parametrize("column,value,word", [(0, 0.0, "mass"), (0, -3.0, "mass"), (3, 0.0, "Izz"),
                                               (4, -0.05, "k_f"), (1, float("nan"), "Ixx")])
def test_bad_params(column, value, word):
    sim = get_simulator("quadrotor")
    p = sim.default_params(1)
    p[0, column] = value
    with pytest.raises(RispError, match=word):
        sim.rollout(p, sim.default_state(1), sim.hover_actions(sim.default_params(1), 2), 2)


def test_bad_effect_param_and_inputs():
    sim = get_simulator("quadrotor", ("motor_lag",))
    p = sim.default_params(1)
    s0 = sim.default_state(1)
    a = sim.hover_actions(p, 2)
    bad = p.clone()
    bad[0, -1] = 0.0
    with pytest.raises(RispError, match="motor_lag.tau"):
        sim.rollout(bad, s0, a, 2)
    with pytest.raises(RispError, match="s0"):
        sim.rollout(p, s0[:, :13], a, 2)  # the thrust states are missing
    with pytest.raises(RispError, match="actions"):
        sim.rollout(p, s0, a[:, :, :3], 2)
    with pytest.raises(RispError, match="actions"):
        sim.rollout(p, s0, a[:, :1], 2)
    with pytest.raises(RispError, match="quaternion"):
        sim.rollout(p, s0 * 2, a, 2)
    with pytest.raises(RispError, match="dt"):
        QuadrotorSimulator(dt=0.0)
    with pytest.raises(RispError, match="unknown effect"):
        get_simulator("quadrotor", ("turbulence",))


def test_ground_effect_centre_scales_total_thrust_without_torque():
    sim = get_simulator("quadrotor", ("ground_effect_centre",))
    p = sim.default_params(1)
    k = p[0, -1].item()
    z = 0.2
    s0 = sim.default_state(1)
    s0[:, 2] = z
    s0[:, 3:7] = euler_to_quat(_t(0.0), _t(0.2), _t(0.1)).reshape(1, 4)  # tilted: the per-rotor variant would torque
    S = sim.rollout(p, s0, sim.hover_actions(p, 1), 1)
    z_hat = GROUND_Z_MIN + GROUND_Z_WIDTH * math.log1p(math.exp((z - GROUND_Z_MIN) / GROUND_Z_WIDTH))
    factor = 1 + k * (ROTOR_RADIUS / (4 * z_hat)) ** 2
    R2 = 1 - 2 * (s0[0, 4] ** 2 + s0[0, 5] ** 2)  # world z of the body z axis
    assert S[0, 1, 9].item() == pytest.approx((G * factor * R2.item() - G) * DT, rel=1e-9)
    assert torch.all(S[0, 1, 10:13] == 0)


@pytest.mark.parametrize("layout, angle", [("+", 0.0), ("x", math.pi / 4)])
def test_layout_and_arm_length_set_the_torques(layout, angle):
    """Extra thrust δ on rotor 0 at L·(cos a, sin a): τ = (L sin a·δ, −L cos a·δ, s_0·k_m·δ)."""
    L, delta = 0.16, 2.0
    sim = QuadrotorSimulator(layout=layout, arm_length=L)
    p = sim.default_params(1)
    assert p[0, 1].item() == pytest.approx(default_inertia(MASS, L)[0])
    u = sim.hover_actions(p, 1)
    u[0, 0, 0] += delta / K_F
    S = sim.rollout(p, sim.default_state(1), u, 1)
    I = p[0, 1:4]
    tau = _t([L * math.sin(angle) * delta, -L * math.cos(angle) * delta, K_M * delta])
    assert torch.allclose(S[0, 1, 10:13], DT * tau / I, rtol=1e-9, atol=1e-15)
    # the defaults are today's vehicle
    base = QuadrotorSimulator()
    assert base.arm_length == ARM_LENGTH and base.default_params(1)[0, 1].item() == pytest.approx(default_inertia()[0])
    with pytest.raises(RispError, match="rotor layout 'h'"):
        QuadrotorSimulator(layout="h")


def test_translational_mode_closed_form_and_gradient():
    """m·v̇ = k_f·c·R(q)e_z + m·g + F: a tilted attitude from the action tilts the thrust; wind adds a force."""
    from risp_tasks.sims.quadrotor import QuadrotorTranslational, make_simulator

    sim = make_simulator(("wind", "motor_lag"), mode="translational", dt=0.002)
    assert isinstance(sim, QuadrotorTranslational) and sim.state_names == ("x", "y", "z", "vx", "vy", "vz", "f0")
    p = sim.default_params(1)
    p[0, sim.param_index("motor_lag.tau")] = 1e-3  # thrust state starts at the command: no lag effect
    s0 = torch.zeros(1, 7, dtype=torch.float64)
    s0[0, 2], s0[0, 6] = 1.0, MASS * G
    q = euler_to_quat(_t(0.0), _t(0.1), _t(0.0)).reshape(1, 1, 4)
    act = torch.cat([torch.full((1, 3, 1), MASS * G, dtype=torch.float64), q.expand(1, 3, 4)], -1)
    S = sim.rollout(p, s0, act, 1)
    R = 1 - 2 * (q[0, 0, 1] ** 2 + q[0, 0, 2] ** 2)
    wind = p[0, 2:5]
    a = (MASS * G * torch.stack([2 * (q[0, 0, 1] * q[0, 0, 3] + q[0, 0, 0] * q[0, 0, 2]),
                                 2 * (q[0, 0, 2] * q[0, 0, 3] - q[0, 0, 0] * q[0, 0, 1]), R]) + wind) / MASS
    a[2] -= G
    assert torch.allclose(S[0, 1, 3:6], 0.002 * a, rtol=1e-9, atol=1e-12)
    p.requires_grad_(True)
    assert gradcheck(lambda pp: sim.rollout(pp, s0, act, 3), (p,), eps=1e-6, atol=1e-6)


def test_hover_with_a_quadratic_thrust_map_stays_put():
    """hover_actions ignored k_f2, so with thrust_quadratic a level vehicle at its 'hover' command climbed."""
    from risp_tasks.sims.quadrotor import make_simulator

    sim = make_simulator(thrust_quadratic=True)
    p = sim.default_params(3)
    p[:, 6] = torch.tensor([0.0, 1e-4, -5e-5], dtype=p.dtype)  # k_f2: none, lifting more, lifting less
    s0 = sim.default_state(3)
    a = sim.hover_actions(p, 100)
    f = p[:, 4] * a[:, 0, 0] + p[:, 6] * a[:, 0, 0] ** 2
    assert torch.allclose(f, p[:, 0] * G / 4, rtol=1e-12)
    assert a[0, 0, 0].item() == pytest.approx(MASS * G / (4 * K_F))
    S = sim.rollout(p, s0, a, 100)
    assert (S[:, :, :3] - s0[:, None, :3]).abs().max() < 1e-9


def test_translational_mode_refuses_options_it_would_ignore():
    from risp_tasks.sims.quadrotor import make_simulator

    assert make_simulator(mode="translational", dt=0.02).dt == pytest.approx(0.02)
    with pytest.raises(RispError, match="the translational quadrotor model takes only dt; arm_length would be ignored"):
        make_simulator(mode="translational", arm_length=0.2)
