"""Quadrotor: a rigid body in free flight driven by four propellers (docs/models.md §2).

Full state (13, + 4 with ``motor_lag``), SI units:

    x y z        position of the centre of mass, world frame [m]
    qw qx qy qz  orientation, unit quaternion, body to world (renormalized every step)
    vx vy vz     linear velocity, world frame [m/s]
    wx wy wz     angular velocity, body frame [rad/s]
    f0 f1 f2 f3  (motor_lag only) thrust of each rotor [N]

Action (4): propeller commands u_i; rotor thrust f_i = k_f·clamp_s(u_i), clamp_s a smooth clamp to [−500, 500]
(docs/models.md §2).  Rotor i sits at (L·cos a_i, L·sin a_i, ROTOR_HEIGHT) in the body frame and spins with sign s_i; its drag produces the yaw torque
s_i·k_m·f_i.  Default: L = ARM_LENGTH = 0.3 m, "+" layout a_i = iπ/2 (see risp_data.envs.quadrotor),
s = (+1, −1, +1, −1); the "x" layout has a_i = π/4 + iπ/2; ``arm_length``, ``layout``, ``rotor_angles``
and ``spin`` are constructor options (real vehicles, docs/measured-data.md).  Integrator: semi-implicit
(symplectic) Euler with dt = 0.01 s (``dt`` option; diagnose sub-steps it, docs/diagnose.md §Time step).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from risp_data.envs.quadrotor import ARM_LENGTH, BODY_HALF_EXTENTS, ROTOR_HEIGHT, ROTOR_RADIUS
from risp_data.errors import RispError

from ._rigid import (
    check_unit_quaternion_state,
    GRAVITY,
    const,
    normalize_quat,
    quat_mul_pure_right,
    quat_outer,
    rigid_to_env_state,
    soft_clamp,
)
from .base import Effect, Simulator, SimulatorSpec

DT = 0.01  # s
MASS = 3.0  # kg (system identification samples it in [2.8, 3.2))
K_F = 0.05  # N per command unit: f_i = k_f·u_i
K_M = 0.02  # m: yaw torque per newton of thrust
SPIN = (1.0, -1.0, 1.0, -1.0)  # s_i: rotors 0, 2 (±x) and 1, 3 (±y) spin in opposite senses
COMMAND_LIMIT = 500.0  # |u_i| ≤ 500 (smooth clamp)
CLAMP_WIDTH = 5.0  # command units: rounding width of the smooth clamp
BODY_MASS_FRACTION = 0.6  # the central box; each of the four motors carries 0.1 of the mass
AIR_DRAG_EPS = 1e-3  # m/s: |v| ≈ sqrt(|v|² + ε²) keeps the quadratic drag differentiable at rest
GROUND_Z_MIN = ROTOR_RADIUS / 4  # m: rotor height below which the ground-effect factor saturates
GROUND_Z_WIDTH = 0.01  # m: rounding width of that saturation


def default_inertia(mass: float = MASS, arm_length: float = ARM_LENGTH) -> tuple[float, float, float]:
    """Principal inertia (Ixx, Iyy, Izz) [kg m²]: a solid box of 0.6·m (half extents BODY_HALF_EXTENTS)
    plus four point motors of 0.1·m at the rotor hubs (``arm_length`` from the centre, in the body plane;
    the same for "+" and "x": Σ m y² over four hubs on a circle is 2·m·L² for any symmetric layout)."""
    a, b, c = BODY_HALF_EXTENTS
    mb, mm = BODY_MASS_FRACTION * mass, (1 - BODY_MASS_FRACTION) / 4 * mass
    arm = 2 * mm * arm_length**2  # two motors on the axis perpendicular to the rotation axis
    return (mb / 3 * (b * b + c * c) + arm, mb / 3 * (a * a + c * c) + arm, mb / 3 * (a * a + b * b) + 2 * arm)


def hover_command(mass, k_f=K_F):
    """u_h = m·g / (4·k_f): the command that holds the quadrotor still out of ground effect (docs §2.2)."""
    return mass * GRAVITY / (4 * k_f)


#: Rotor azimuths a_i [rad] of the named layouts (rotor i at L·(cos a_i, sin a_i, 0), counter-clockwise from +x).
LAYOUTS = {"+": tuple(i * math.pi / 2 for i in range(4)), "x": tuple(math.pi / 4 + i * math.pi / 2 for i in range(4))}


def ground_factor(k, z, radius=ROTOR_RADIUS):
    """1 + k·(R / (4·ẑ))², ẑ = z_min + softplus(z − z_min) (Cheeseman–Bennett, smoothly floored height)."""
    z_hat = GROUND_Z_MIN + torch.nn.functional.softplus(z - GROUND_Z_MIN, beta=1.0 / GROUND_Z_WIDTH, threshold=40.0)
    return 1.0 + k * (radius / (4.0 * z_hat)) ** 2


STATE_NAMES = ("x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz")
_INF = float("inf")
_POS = (1e-9, _INF)

EFFECTS = {
    "rotor_drag": Effect(
        "rotor_drag", ("dx", "dy", "dz"), (0.9, 0.9, 0.3), ((0.0, 3.0),) * 3,
        "linear rotor drag F = −R·diag(dx, dy, dz)·Rᵀ·v (body-frame coefficients, N·s/m)",
        bounds=((0.0, _INF),) * 3, units=("N s/m",) * 3),
    "air_drag": Effect(
        "air_drag", ("c",), (0.05,), ((0.0, 0.5),),
        "quadratic air drag F = −c·|v|·v (N·s²/m²)", bounds=((0.0, _INF),), units=("N s^2/m^2",)),
    "wind": Effect(
        "wind", ("fx", "fy", "fz"), (1.0, 0.0, 0.0), ((-5.0, 5.0),) * 3,
        "constant world-frame force (N)", units=("N",) * 3),
    "motor_lag": Effect(
        "motor_lag", ("tau",), (0.05,), ((0.01, 0.2),),
        "first-order motor lag: rotor thrust f follows k_f·u with time constant tau (s); adds 4 thrust states",
        bounds=((1e-4, _INF),), units=("s",), state_names=("f0", "f1", "f2", "f3")),
    "ground_effect": Effect(
        "ground_effect", ("k",), (1.0,), ((0.0, 2.0),),
        "thrust scaled by 1 + k·(R_rotor / (4·ẑ_i))² near the floor z = 0 (ẑ_i: smoothly floored rotor height)",
        bounds=((0.0, _INF),), units=("1",)),
    "ground_effect_centre": Effect(
        "ground_effect_centre", ("k",), (1.0,), ((0.0, 2.0),),
        "total thrust scaled by 1 + k·(R_rotor / (4·ẑ))² with ẑ the (smoothly floored) height of the centre; "
        "no torque (the variant of ground_effect where the whole vehicle sees one cushion)",
        bounds=((0.0, _INF),), units=("1",)),
}

SPEC = SimulatorSpec(
    env="quadrotor",
    dt=DT,
    state_names=STATE_NAMES,
    base_param_names=("mass", "Ixx", "Iyy", "Izz", "k_f", "k_m"),
    base_param_defaults=(MASS, *default_inertia(MASS), K_F, K_M),
    action_dim=4,
    available_effects=EFFECTS,
    base_param_bounds=(_POS, _POS, _POS, _POS, _POS, (0.0, _INF)),
    base_param_ranges=((2.8, 3.2), (0.04, 0.08), (0.04, 0.08), (0.08, 0.15), (0.04, 0.06), (0.01, 0.03)),
    base_param_units=("kg", "kg m^2", "kg m^2", "kg m^2", "N", "m"),
)


@dataclass(frozen=True)
class _Consts:
    """Per-rollout tensors derived from params (computed once, reused every step)."""

    h: float
    inv_m: torch.Tensor  # (B, 1)
    inertia: torch.Tensor  # (B, 3)
    inv_inertia: torch.Tensor  # (B, 3)
    tau_scale: torch.Tensor  # (B, 3) = (L, L, k_m)
    mix: torch.Tensor  # (4, 3): τ = (f @ mix) ⊙ tau_scale
    gravity: torch.Tensor  # (3,)
    rotor_drag: torch.Tensor | None  # (B, 3)
    air_drag: torch.Tensor | None  # (B, 1)
    wind: torch.Tensor | None  # (B, 3)
    lag_alpha: torch.Tensor | None  # (B, 1) = 1 − exp(−h/τ)
    ground_k: torch.Tensor | None  # (B, 1)
    ground_centre_k: torch.Tensor | None  # (B, 1)
    rotor_pos: torch.Tensor  # (3, 4) rotor hubs in the body frame (ground-effect heights)


class QuadrotorSimulator(Simulator):
    """Differentiable quadrotor (docs/models.md §2).

    Options (defaults = the rendered vehicle): ``dt`` [s]; ``arm_length`` L [m]; ``layout`` "+" or "x";
    ``rotor_angles`` (4 azimuths [rad], overrides ``layout``) and ``spin`` (4 signs s_i) for vehicles
    whose motor numbering differs (e.g. PX4's quad-X).  The default inertia follows L.
    """

    def __init__(self, effects: tuple[str, ...] | list[str] = (), dt: float = DT, arm_length: float = ARM_LENGTH,
                 layout: str = "+", rotor_angles: tuple[float, ...] | None = None, spin: tuple[float, ...] = SPIN,
                 thrust_quadratic: bool = False):
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise RispError(f"dt must be a positive number of seconds, got {dt!r}")
        if not (isinstance(arm_length, (int, float)) and math.isfinite(arm_length) and arm_length > 0):
            raise RispError(f"arm_length must be a positive number of metres, got {arm_length!r}")
        if rotor_angles is None:
            if str(layout).lower() not in LAYOUTS:
                raise RispError(f"rotor layout {layout!r} is not known; choose '+' or 'x' (or give rotor_angles)")
            rotor_angles = LAYOUTS[str(layout).lower()]
        if len(rotor_angles) != 4 or len(spin) != 4 or any(abs(abs(float(x)) - 1) > 1e-9 for x in spin):
            raise RispError(f"rotor_angles and spin need 4 entries each (spin ±1), got {rotor_angles!r}, {spin!r}")
        self.arm_length = float(arm_length)
        self.rotor_angles = tuple(float(a) for a in rotor_angles)
        self.spin = tuple(float(x) for x in spin)
        defaults = SPEC.base_param_defaults
        if self.arm_length != ARM_LENGTH:
            defaults = (MASS, *default_inertia(MASS, self.arm_length), K_F, K_M)
        self.spec = dataclasses.replace(SPEC, dt=float(dt), base_param_defaults=defaults)
        if thrust_quadratic:
            # a quadratic thrust map f = k_f·u + k_f2·u² (normalised commands); k_f2 is appended so that the
            # other parameters keep their positions
            self.spec = dataclasses.replace(
                self.spec, base_param_names=SPEC.base_param_names + ("k_f2",), base_param_defaults=defaults + (0.0,),
                base_param_bounds=SPEC.base_param_bounds + ((-_INF, _INF),),
                base_param_ranges=SPEC.base_param_ranges + ((-0.05, 0.05),), base_param_units=SPEC.base_param_units + ("N",))
        self.thrust_quadratic = bool(thrust_quadratic)
        super().__init__(effects)

    # -- layout ---------------------------------------------------------------------------------
    def default_state(self, batch: int = 1, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """At rest 1 m above the floor, level; thrust states (motor_lag) at the default hover thrust."""
        s = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0] + [0.0] * 6
        if "motor_lag" in self.effects:
            s += [MASS * GRAVITY / 4] * 4
        return torch.tensor(s, dtype=dtype).expand(batch, -1).clone()

    def hover_actions(self, params: torch.Tensor, steps: int) -> torch.Tensor:
        """(B, steps, 4) hover commands for each batch row of ``params``: u_h = m g / (4 k_f), or with
        ``thrust_quadratic`` the root of k_f u + k_f2 u² = m g / 4 nearest to it (docs §2.2)."""
        m, k_f = params[:, 0], params[:, self.param_index("k_f")]
        u = hover_command(m, k_f)
        if self.thrust_quadratic:
            k2 = params[:, 6]
            # 2c / (b + sqrt(b² + 4ac)): the same root as (−b + sqrt(…)) / (2a), stable as k_f2 → 0 (then m g / 4k_f)
            quarter = m * GRAVITY / 4
            u = 2 * quarter / (k_f + torch.sqrt(k_f * k_f + 4 * k2 * quarter))
        return u[:, None, None].expand(-1, steps, 4).clone()

    def check_state(self, s0: torch.Tensor) -> None:
        check_unit_quaternion_state(s0)

    def to_env_state(self, states: torch.Tensor) -> torch.Tensor:
        """(..., X) -> (..., 6) = (x, y, z, yaw, pitch, roll) of risp_data's quadrotor environment."""
        return rigid_to_env_state(states)

    # -- dynamics -------------------------------------------------------------------------------
    def _consts(self, params: torch.Tensor) -> _Consts:
        B, like = params.shape[0], params
        mass = params[:, 0:1]
        inertia = params[:, 1:4]
        k_m = params[:, 5:6]
        L = torch.full((B, 2), self.arm_length, dtype=params.dtype, device=params.device)
        angles = self.rotor_angles
        # torque of rotor i about the centre: r_i × (0, 0, f_i) = L·(sin a_i, −cos a_i)·f_i, yaw s_i·k_m·f_i
        clean = lambda v: 0.0 if abs(v) < 1e-12 else v  # noqa: E731  (exact zeros for the "+" layout)
        mix = torch.tensor([[clean(math.sin(a)), clean(-math.cos(a)), s] for a, s in zip(angles, self.spin)],
                           dtype=like.dtype, device=like.device)
        rotor_pos = torch.tensor([[self.arm_length * math.cos(a) for a in angles],
                                  [self.arm_length * math.sin(a) for a in angles],
                                  [ROTOR_HEIGHT] * 4], dtype=like.dtype, device=like.device)

        def eff(name):
            return self.effect_params(params, name)

        tau = eff("motor_lag")
        return _Consts(
            h=self.dt,
            inv_m=1.0 / mass,
            inertia=inertia,
            inv_inertia=1.0 / inertia,
            tau_scale=torch.cat([L, k_m], 1),
            mix=mix,
            gravity=torch.tensor([0.0, 0.0, -GRAVITY], dtype=like.dtype, device=like.device),
            rotor_drag=eff("rotor_drag"),
            air_drag=eff("air_drag"),
            wind=eff("wind"),
            lag_alpha=None if tau is None else -torch.expm1(-self.dt / tau),
            ground_k=eff("ground_effect"),
            ground_centre_k=eff("ground_effect_centre"),
            rotor_pos=rotor_pos,
        )

    def _commanded_thrust(self, params: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """k_f · clamp_s(u) (docs §2.2) [+ k_f2 · clamp_s(u)² with ``thrust_quadratic``], for any leading
        shape of ``actions`` (B, ..., 4)."""
        u = soft_clamp(actions, -COMMAND_LIMIT, COMMAND_LIMIT, CLAMP_WIDTH)
        shape = (-1,) + (1,) * (actions.ndim - 1)
        f = params[:, 4].reshape(shape) * u
        if self.thrust_quadratic:
            f = f + params[:, 6].reshape(shape) * u * u
        return f

    @staticmethod
    def _advance(c: _Consts, p, q, v, w, f_state, f_cmd):
        """One semi-implicit Euler step (docs §2.4): forces at (q, v, ω), then v, ω, then p, q."""
        h = c.h
        qq = quat_outer(q)  # (B, 16)

        # Rotor thrusts: motor lag (exact first-order response over the step), then ground effect.
        if c.lag_alpha is not None:
            f_state = f_state + c.lag_alpha * (f_cmd - f_state)
            f = f_state
        else:
            f = f_cmd
        if c.ground_k is not None:
            z_rotor = p[:, 2:3] + (qq @ const("R_row2", q)) @ c.rotor_pos  # (B, 4) world heights of the hubs
            f = f * ground_factor(c.ground_k, z_rotor)
        total = f.sum(1, keepdim=True)
        if c.ground_centre_k is not None:
            total = total * ground_factor(c.ground_centre_k, p[:, 2:3])

        # Linear acceleration: thrust along the body z axis, gravity and the enabled external forces.
        z_body = qq @ const("R_col2", q)  # (B, 3)
        force = total * z_body
        if c.rotor_drag is not None:
            R = (qq @ const("R", q)).unflatten(-1, (3, 3))
            v_body = (v.unsqueeze(1) @ R).squeeze(1)  # Rᵀ v
            force = force - (R @ (c.rotor_drag * v_body).unsqueeze(-1)).squeeze(-1)
        if c.air_drag is not None:
            speed = torch.sqrt((v * v).sum(1, keepdim=True) + AIR_DRAG_EPS**2)
            force = force - c.air_drag * speed * v
        if c.wind is not None:
            force = force + c.wind
        v_new = v + h * (force * c.inv_m + c.gravity)

        # Euler's equations in the body frame: I ω̇ = τ − ω × I ω.
        torque = (f @ c.mix) * c.tau_scale
        w_dot = (torque - torch.linalg.cross(w, c.inertia * w)) * c.inv_inertia
        w_new = w + h * w_dot

        p_new = p + h * v_new
        q_new = normalize_quat(q + (0.5 * h) * quat_mul_pure_right(q, w_new))
        return p_new, q_new, v_new, w_new, f_state

    def _split(self, state: torch.Tensor):
        p, q, v, w = state[:, 0:3], state[:, 3:7], state[:, 7:10], state[:, 10:13]
        f_state = state[:, 13:17] if "motor_lag" in self.effects else None
        return p, normalize_quat(q), v, w, f_state

    def step(self, params: torch.Tensor, state: torch.Tensor, action: torch.Tensor | None, t: int) -> torch.Tensor:
        """One step of dt (docs §2.4); ``action`` (B, 4) are the raw propeller commands."""
        c = self._consts(params)
        p, q, v, w, fs = self._split(state)
        out = self._advance(c, p, q, v, w, fs, self._commanded_thrust(params, action))
        return torch.cat([x for x in out if x is not None], 1)

    def rollout(self, params: torch.Tensor, s0: torch.Tensor, actions: torch.Tensor | None, steps: int) -> torch.Tensor:
        """Same result as repeated :meth:`step`, with the per-rollout work hoisted out of the loop."""
        self.check_inputs(params, s0, actions, steps)
        c = self._consts(params)
        f_cmd = self._commanded_thrust(params, actions[:, :steps])  # (B, T, 4)
        cur = self._split(s0)
        traj = []
        for t in range(steps):
            cur = self._advance(c, *cur, f_cmd[:, t])
            traj.append([x for x in cur if x is not None])
        if not traj:
            return s0.unsqueeze(1)
        later = torch.cat([torch.stack(parts, 1) for parts in zip(*traj)], -1)  # (B, steps, X)
        return torch.cat([s0.unsqueeze(1), later], 1)


def make_simulator(effects: tuple[str, ...] = (), mode: str = "full", **options):
    """The quadrotor simulator with the named effects; ``options``: dt (s), arm_length (m), layout ("+"/"x"),
    rotor_angles (rad), spin (±1 each).  ``mode="translational"``: :class:`QuadrotorTranslational` (dt only)."""
    if mode == "translational":
        ignored = sorted(set(options) - {"dt"})
        if ignored:  # the vehicle's geometry does not enter the translational model: say so, not ignore it
            raise RispError(f"the translational quadrotor model takes only dt; {', '.join(ignored)} would be ignored")
        return QuadrotorTranslational(effects, dt=options.get("dt", DT))
    if mode != "full":
        raise RispError(f"quadrotor mode {mode!r} is not known; choose 'full' or 'translational'")
    return QuadrotorSimulator(effects, **options)


# ------------------------------------------------------------------------------------------------
# translational mode: collective thrust with the attitude taken from the data (docs/models.md §2)
# ------------------------------------------------------------------------------------------------
TRANSLATIONAL_EFFECTS = ("rotor_drag", "air_drag", "wind", "motor_lag", "ground_effect_centre")
TRANSLATIONAL_SPEC = SimulatorSpec(
    env="quadrotor",
    dt=DT,
    state_names=("x", "y", "z", "vx", "vy", "vz"),
    base_param_names=("mass", "k_f"),
    base_param_defaults=(MASS, 1.0),
    action_dim=5,
    available_effects={k: (dataclasses.replace(EFFECTS[k], state_names=("f0",)) if k == "motor_lag" else EFFECTS[k])
                       for k in TRANSLATIONAL_EFFECTS},
    base_param_bounds=(_POS, _POS),
    base_param_ranges=((2.8, 3.2), (0.5, 2.0)),
    base_param_units=("kg", "N"),
)


class QuadrotorTranslational(Simulator):
    """Translational dynamics only, as much of the multirotor aerodynamics literature models them:

        m·v̇ = k_f·c·g_e(z)·R(q)·e_z + m·g + F_effects(v, R),    ṗ = v

    State (6, + the collective thrust with ``motor_lag``): x y z vx vy vz [, f0].  Action (5): the collective
    command c (newtons with k_f = 1, or a normalised throttle with a fitted k_f) and the measured attitude
    quaternion (qw, qx, qy, qz), both held over the step.  Effects: rotor_drag (body-frame linear drag
    with R from the action), air_drag, wind, motor_lag (on the collective), ground_effect_centre.  Integrator:
    semi-implicit Euler with step ``dt``.
    """

    spec = TRANSLATIONAL_SPEC

    def __init__(self, effects: tuple[str, ...] | list[str] = (), dt: float = DT):
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise RispError(f"dt must be a positive number of seconds, got {dt!r}")
        self.spec = dataclasses.replace(TRANSLATIONAL_SPEC, dt=float(dt))
        super().__init__(effects)

    def to_env_state(self, states: torch.Tensor) -> torch.Tensor:
        raise RispError("the translational quadrotor model has no attitude state to render")

    def step(self, params: torch.Tensor, state: torch.Tensor, action: torch.Tensor | None, t: int) -> torch.Tensor:
        h = self.dt
        p, v = state[:, 0:3], state[:, 3:6]
        cmd = params[:, 1:2] * action[:, 0:1]
        q = normalize_quat(action[:, 1:5])
        qq = quat_outer(q)
        tau = self.effect_params(params, "motor_lag")
        if tau is not None:
            f = state[:, 6:7] + (-torch.expm1(-h / tau)) * (cmd - state[:, 6:7])
        else:
            f = cmd
        thrust = f
        k_ge = self.effect_params(params, "ground_effect_centre")
        if k_ge is not None:
            thrust = thrust * ground_factor(k_ge, p[:, 2:3])
        force = thrust * (qq @ const("R_col2", q))
        drag = self.effect_params(params, "rotor_drag")
        if drag is not None:
            R = (qq @ const("R", q)).unflatten(-1, (3, 3))
            v_body = (v.unsqueeze(1) @ R).squeeze(1)
            force = force - (R @ (drag * v_body).unsqueeze(-1)).squeeze(-1)
        c = self.effect_params(params, "air_drag")
        if c is not None:
            force = force - c * torch.sqrt((v * v).sum(1, keepdim=True) + AIR_DRAG_EPS**2) * v
        wind = self.effect_params(params, "wind")
        if wind is not None:
            force = force + wind
        g = torch.tensor([0.0, 0.0, -GRAVITY], dtype=v.dtype, device=v.device)
        v_new = v + h * (force / params[:, 0:1] + g)
        p_new = p + h * v_new
        parts = [p_new, v_new] + ([f] if tau is not None else [])
        return torch.cat(parts, 1)
