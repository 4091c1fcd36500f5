"""Hand: a fixed palm with five torque-driven planar finger chains (13 revolute joints).

Equations, units and defaults: docs/models/hand.md.  Summary:

* every joint of finger f flexes about the same world axis (FINGER_AXES[f] = x), so each finger is a
  planar serial chain of uniform cylindrical links moving in the plane ⊥ x (Sec. "Kinematics");
* M(q) q̈ + h(q, q̇) = u − K q − b(q) − c q̇ − τ_fric(q̇) + τ_grav(q)      (Sec. "Equations of motion")
  with the mass matrix M and Coriolis/centrifugal term h of the chain, per-finger joint stiffness K,
  a smooth barrier b enforcing the joint limits ±π/4, viscous damping c and the optional effects;
* linearly implicit Euler (Sec. "Integrator"): the stiff per-joint terms (spring, barrier, damping,
  friction) are linearised about the predicted angles q + dt·q̇ and treated implicitly, the chain's
  inertial coupling (M, h, gravity at the start of the step) explicitly, so the barrier may be stiff at
  dt = 0.01 s;
* actions: one torque per finger, applied to every joint of that finger; ``hand_torque_schedule``
  builds the paper's sine schedule from (m, δ) differentiably.

State (26) = joint angles [rad] (13, order of risp_data.envs.hand.JOINT_NAMES) then joint angular
velocities [rad/s] (13).  ``to_env_state`` returns the 13 angles (the environment's state vector).
"""

from __future__ import annotations

import math

import torch

from risp_data.envs import hand as geometry
from risp_data.errors import RispError

from ._smooth import smooth_clamp, softplus_width
from .base import Effect, Simulator, SimulatorSpec

# -- model constants (docs/models/hand.md, "Constants") ---------------------------------------------
DT = 0.01  # s, one control step
LINEAR_DENSITY = 1.0  # kg/m: link mass = LINEAR_DENSITY · link length (uniform solid cylinders)
BASE_DAMPING = 0.05  # N·m·s/rad, viscous damping present in every joint (the effect adds to it)
LIMIT_STIFFNESS = 1000.0  # N·m/rad, slope of the joint-limit barrier beyond ±π/4
LIMIT_WIDTH = 0.01  # rad, width over which the barrier's corner is rounded
FRICTION_VELOCITY = 0.1  # rad/s, smoothing velocity of the Coulomb friction tanh
SCHEDULE_PERIOD = 40.0  # steps, T of the torque schedule
N_FINGERS = len(geometry.FINGERS)
N_JOINTS = len(geometry.JOINT_NAMES)
MAX_LINKS = max(geometry.JOINTS_PER_FINGER)

EFFECTS = {
    "joint_damping": Effect(
        "joint_damping", ("coefficient",), (0.05,), ((0.0, 0.5),),
        "extra viscous torque −c·q̇ in every joint [N·m·s/rad], added to the base damping 0.05",
        bounds=((0.0, math.inf),), units=("N·m·s/rad",),
    ),
    "joint_friction": Effect(
        "joint_friction", ("torque",), (0.02,), ((0.0, 0.1),),
        "smoothed Coulomb torque −μ·tanh(q̇ / 0.1 rad/s) in every joint [N·m]",
        bounds=((0.0, math.inf),), units=("N·m",),
    ),
    "gravity": Effect(
        "gravity", ("g",), (9.81,), ((0.0, 9.81),),
        "gravitational acceleration along world −z acting on the links [m/s²]",
        bounds=((0.0, math.inf),), units=("m/s²",),
    ),
}

SPEC = SimulatorSpec(
    env="hand",
    dt=DT,
    state_names=tuple(geometry.JOINT_NAMES) + tuple(f"{n}_vel" for n in geometry.JOINT_NAMES),
    base_param_names=tuple(f"stiffness_{f}" for f in geometry.FINGERS),
    base_param_defaults=(1.0,) * N_FINGERS,
    action_dim=N_FINGERS,
    available_effects=EFFECTS,
    base_param_bounds=((0.0, math.inf),) * N_FINGERS,
    base_param_ranges=((0.0, 1.0),) * N_FINGERS,
    base_param_units=("N·m/rad",) * N_FINGERS,
)


def _finger_tables():
    """Padded (5, 3) tables of the per-link constants; a padded link has zero length and mass."""
    joint_index = [[N_JOINTS] * MAX_LINKS for _ in range(N_FINGERS)]  # N_JOINTS -> the zero column
    mask = [[0.0] * MAX_LINKS for _ in range(N_FINGERS)]
    length_perp = [[0.0] * MAX_LINKS for _ in range(N_FINGERS)]
    mass = [[0.0] * MAX_LINKS for _ in range(N_FINGERS)]
    inertia = [[0.0] * MAX_LINKS for _ in range(N_FINGERS)]
    phi0 = []
    j = 0
    for f, n in enumerate(geometry.JOINTS_PER_FINGER):
        axis = torch.tensor(geometry.FINGER_AXES[f], dtype=torch.float64)
        d = torch.tensor(geometry.FINGER_DIRECTIONS[f], dtype=torch.float64)
        d = d / d.norm()
        cos_axis = float(d @ axis)  # the link's component along the joint axis does not move
        sin_axis = math.sqrt(max(0.0, 1.0 - cos_axis**2))
        # planar coordinates (a, b) = (y, z) for axis x: rotation about +x by θ maps (y, z) to
        # (y cos θ − z sin θ, y sin θ + z cos θ), i.e. an ordinary 2-D rotation of (y, z)
        phi0.append(math.atan2(float(d[2]), float(d[1])))
        for k in range(n):
            L = geometry.LINK_LENGTHS[f][k]
            m = LINEAR_DENSITY * L
            r = geometry.LINK_RADIUS
            i_perp = m * (3 * r * r + L * L) / 12.0  # solid cylinder about a transverse axis through its CoM
            i_par = m * r * r / 2.0  # about its own axis
            joint_index[f][k] = j
            mask[f][k] = 1.0
            length_perp[f][k] = L * sin_axis
            mass[f][k] = m
            inertia[f][k] = i_perp + (i_par - i_perp) * cos_axis**2  # about the joint axis
            j += 1
    return joint_index, mask, length_perp, mass, inertia, phi0


class HandSimulator(Simulator):
    """Five planar finger chains on a fixed palm; see the module docstring and docs/models/hand.md."""

    spec = SPEC

    def __init__(self, effects=()):
        super().__init__(effects)
        self._cache: dict[torch.dtype, dict[str, torch.Tensor]] = {}

    # -- constants ----------------------------------------------------------------------------------
    def _consts(self, dtype: torch.dtype) -> dict[str, torch.Tensor]:
        if dtype not in self._cache:
            joint_index, mask, length_perp, mass, inertia, phi0 = _finger_tables()
            t = lambda v: torch.tensor(v, dtype=dtype)  # noqa: E731
            mask_t = t(mask)
            upper = torch.triu(torch.ones(MAX_LINKS, MAX_LINKS, dtype=dtype))  # U[j, i] = 1 if link i is moved by joint j
            inertia_t = t(inertia)
            # rotational part of M, constant: Σ_i I_i U[j,i] U[k,i], plus 1 on the padded joints' diagonal
            m_rot = torch.einsum("ji,ki,fi->fjk", upper, upper, inertia_t) + torch.diag_embed(1.0 - mask_t)
            keep = [f * MAX_LINKS + k for f, n in enumerate(geometry.JOINTS_PER_FINGER) for k in range(n)]
            self._cache[dtype] = {
                "joint_index": torch.tensor(joint_index, dtype=torch.long).flatten(),
                "keep": torch.tensor(keep, dtype=torch.long),
                "mask": mask_t,
                "m_rot": m_rot,
                "phi0": t(phi0)[:, None],
                "quarter": t([0.0, math.pi / 2]),
                "length_vec": t(length_perp)[..., None],
                "mass_vec": t(mass)[:, None, :, None],
                "upper_vec": upper[:, :, None],
                "cross": t([1.0, -1.0]),
                "finger_of_joint": torch.tensor(
                    [f for f, n in enumerate(geometry.JOINTS_PER_FINGER) for _ in range(n)], dtype=torch.long
                ),
            }
        return self._cache[dtype]

    def _effect_param(self, params: torch.Tensor, effect: str, name: str):
        if effect not in self.effects:
            return None
        return params[:, self.param_index(f"{effect}.{name}")]

    # -- padded layout helpers ---------------------------------------------------------------------
    def _pad(self, x: torch.Tensor, c) -> torch.Tensor:
        """(B, 13) -> (B, 5, 3), zeros in the padded slots."""
        x = torch.nn.functional.pad(x, (0, 1))
        return x[:, c["joint_index"]].view(x.shape[0], N_FINGERS, MAX_LINKS)

    def _unpad(self, x: torch.Tensor, c) -> torch.Tensor:
        return x.reshape(x.shape[0], N_FINGERS * MAX_LINKS)[:, c["keep"]]

    # -- dynamics (docs/models/hand.md, "Equations of motion" and "Integrator") ------------------------
    def _coefficients(self, params: torch.Tensor, c):
        """Per-rollout constants: stiffness (B,5,1), damping (B,1,1), friction (B,1,1) or None, g or None."""
        stiffness = params[:, :N_FINGERS, None]
        damping = torch.full_like(params[:, :1, None], BASE_DAMPING)
        extra = self._effect_param(params, "joint_damping", "coefficient")
        if extra is not None:
            damping = damping + extra[:, None, None]
        mu = self._effect_param(params, "joint_friction", "torque")
        g = self._effect_param(params, "gravity", "g")
        return stiffness, damping, (None if mu is None else mu[:, None, None]), (None if g is None else g[:, None, None])

    def _inertial_terms(self, q, v, c):
        """Mass matrix M (B,5,3,3), Coriolis/centrifugal torques h (B,5,3) and m_i·d[j,i] (B,5,3,3,2)."""
        # kinematics in the finger plane: absolute link angles φ, unit vectors e = (cos φ, sin φ)
        phi = torch.cumsum(q, -1) + c["phi0"]  # (B,5,3)
        omega = torch.cumsum(v, -1)  # φ̇
        e = torch.cos(phi[..., None] - c["quarter"])  # (B,5,3,2); sin φ = cos(φ − π/2)
        link = c["length_vec"] * e  # ℓ_i = L_i e_i
        tip = torch.cumsum(link, -2)  # end of link i
        joint_pos = tip - link  # p_j
        com_pos = tip - 0.5 * link  # p_ci (uniform links: CoM at mid-length)
        # d[j, i] = p_ci − p_j for links i moved by joint j (U[j, i] = 1), else 0
        d = (com_pos[:, :, None] - joint_pos[:, :, :, None]) * c["upper_vec"]  # (B,5,3,3,2)
        md = d * c["mass_vec"]
        # mass matrix  M_jk = Σ_i m_i d[j,i]·d[k,i] + Σ_i I_i U[j,i] U[k,i]
        M = (md[:, :, :, None] * d[:, :, None]).sum((-1, -2)) + c["m_rot"]
        # Coriolis/centrifugal h_j = Σ_i m_i (R90 d[j,i]) · a_ci with the bias acceleration
        # a_ci = −Σ_{l<i} φ̇_l² ℓ_l − φ̇_i² ℓ_i / 2  (the CoM acceleration when q̈ = 0), and
        # (R90 d) · a = d_y a_z − d_z a_y = d · (a_z, −a_y)
        w2_link = (omega * omega)[..., None] * link
        a_com = 0.5 * w2_link - torch.cumsum(w2_link, -2)
        h = (md * (a_com.flip(-1) * c["cross"])[:, :, None]).sum((-1, -2))
        return M, h, md

    def _padded_step(self, q, v, u, coeffs, c):
        """One linearly implicit Euler step on padded (B, 5, 3) angles q, velocities v and torques u (B, 5)."""
        stiffness, damping, mu, g = coeffs
        M, h, md = self._inertial_terms(q, v, c)
        # diagonal joint torques, linearised about the predicted angles q̃ = q + dt·q̇ (so that the
        # barrier acts in the step that would cross the limit) and the current rates q̇
        lim = geometry.JOINT_LIMIT
        q_pred = q + DT * v
        upper, lower = q_pred - lim, -q_pred - lim
        barrier = LIMIT_STIFFNESS * (softplus_width(upper, LIMIT_WIDTH) - softplus_width(lower, LIMIT_WIDTH))
        barrier_dq = LIMIT_STIFFNESS * (torch.sigmoid(upper / LIMIT_WIDTH) + torch.sigmoid(lower / LIMIT_WIDTH))
        force = u[:, :, None] * c["mask"] - stiffness * q_pred - barrier - damping * v - h
        k_eff = stiffness + barrier_dq  # −∂f/∂q (diagonal part)
        c_eff = damping  # −∂f/∂q̇ (diagonal part)
        if mu is not None:
            s = torch.tanh(v / FRICTION_VELOCITY)
            force = force - mu * s
            c_eff = c_eff + mu * (1.0 - s * s) / FRICTION_VELOCITY
        if g is not None:
            force = force - g * md[..., 0].sum(-1)  # τ_j = −g Σ_i m_i U[j,i] (p_ci − p_j)_y
        # f(q⁺, q̇⁺) ≈ f(q̃, q̇) − K (q⁺ − q̃) − C Δq̇ with q⁺ − q̃ = dt Δq̇:
        # (M + dt·C + dt²·K) Δq̇ = dt · f(q̃, q̇)
        A = M + torch.diag_embed(DT * c_eff + DT * DT * k_eff)
        rhs = DT * force
        dv = _solve_symmetric_3x3(A, rhs) * c["mask"]
        v_next = v + dv
        q_next = q + DT * v_next
        return q_next, v_next

    def step(self, params, state, action, t):
        c = self._consts(state.dtype)
        q, v = self._pad(state[:, :N_JOINTS], c), self._pad(state[:, N_JOINTS:], c)
        q, v = self._padded_step(q, v, action, self._coefficients(params, c), c)
        return torch.cat((self._unpad(q, c), self._unpad(v, c)), -1)

    def rollout(self, params, s0, actions, steps):
        """Integrate ``steps`` steps (docs/models/hand.md); returns (B, steps + 1, 26), row 0 = s0."""
        self.check_inputs(params, s0, actions, steps)
        c = self._consts(s0.dtype)
        coeffs = self._coefficients(params, c)
        q, v = self._pad(s0[:, :N_JOINTS], c), self._pad(s0[:, N_JOINTS:], c)
        qs, vs = [q], [v]
        for t in range(steps):
            q, v = self._padded_step(q, v, actions[:, t], coeffs, c)
            qs.append(q)
            vs.append(v)
        B = s0.shape[0]
        keep = c["keep"]
        q_all = torch.stack(qs, 1).reshape(B, steps + 1, N_FINGERS * MAX_LINKS)[:, :, keep]
        v_all = torch.stack(vs, 1).reshape(B, steps + 1, N_FINGERS * MAX_LINKS)[:, :, keep]
        return torch.cat((q_all, v_all), -1)

    def to_env_state(self, states: torch.Tensor) -> torch.Tensor:
        """Full states (..., 26) -> joint angles (..., 13), the risp_data hand state vector."""
        self.check_full_states(states)
        return states[..., :N_JOINTS]

    def default_state(self, batch: int = 1, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """All joints at the rest angle 0 with zero velocity: (batch, 26)."""
        return torch.zeros(batch, len(self.state_names), dtype=dtype)

    def rest_state(self, batch: int = 1, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Alias of :meth:`default_state` (kept for existing callers)."""
        return self.default_state(batch, dtype)


def _solve_symmetric_3x3(A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """A⁻¹ b for symmetric 3×3 A (…, 3, 3) by the adjugate: A⁻¹ = cof(A)ᵀ / det A.

    Row i of cof(A) is r_{i+1} × r_{i+2} (r_i the rows of A).  A handful of elementwise kernels instead of
    a batched LAPACK call: LAPACK's threading made ``torch.linalg.solve`` 10–25× slower on the shared
    2-core machine, and A = M + dt·C + dt²·K is symmetric positive definite and well conditioned.
    """
    cof = torch.linalg.cross(A.roll(-1, dims=-2), A.roll(-2, dims=-2), dim=-1)
    det = (A[..., 0, :] * cof[..., 0, :]).sum(-1, keepdim=True)
    return (cof * b.unsqueeze(-2)).sum(-1) / det


def hand_torque_schedule(
    m: torch.Tensor,
    delta: torch.Tensor,
    steps: int,
    period: float = SCHEDULE_PERIOD,
    smoothing: float = 0.0,
) -> torch.Tensor:
    """Per-finger torques u_t = m · sin(2π · clamp((t − δ)/T, 0, 1)), t = 0 … steps−1 (paper, hand task).

    m (B, 5) in [0, 1] [N·m], delta (B, 5) in [0, 40] [steps] -> actions (B, steps, 5).  The default
    ``smoothing=0`` is the paper's formula exactly (hard clamp).  ``smoothing > 0`` (opt-in, e.g. 1 step
    when optimising δ) replaces the clamp by ``_smooth.smooth_clamp`` with a corner width of ``smoothing``
    steps, so the torque depends smoothly on δ even where the hard clamp would bind; it then differs
    from the exact formula by up to ~11 % of the peak next to the corners (docs/models/hand.md,
    "Torque schedule").
    """
    for name, x in (("m", m), ("delta", delta)):
        if not torch.is_tensor(x) or x.ndim != 2 or x.shape[1] != N_FINGERS:
            shape = tuple(x.shape) if torch.is_tensor(x) else type(x).__name__
            raise RispError(f"{name} must have shape (B, {N_FINGERS}), got {shape}")
        if not torch.isfinite(x).all():
            raise RispError(f"{name} contains NaN/inf")
    if m.shape[0] != delta.shape[0]:
        raise RispError(f"m and delta disagree on the batch size ({m.shape[0]} vs {delta.shape[0]})")
    if bool((m < 0).any() or (m > 1).any()):
        raise RispError("m must lie in [0, 1]")
    if bool((delta < 0).any() or (delta > 40).any()):
        raise RispError("delta must lie in [0, 40]")
    if not isinstance(steps, int) or steps < 0:
        raise RispError(f"steps must be a non-negative int, got {steps!r}")
    if not period > 0 or smoothing < 0:
        raise RispError(f"period must be > 0 and smoothing >= 0, got {period!r}, {smoothing!r}")
    t = torch.arange(steps, dtype=m.dtype)
    phase = (t[None, None, :] - delta[:, :, None]) / period  # (B, 5, steps)
    phase = smooth_clamp(phase, 0.0, 1.0, smoothing / period)
    return (m[:, :, None] * torch.sin(2.0 * math.pi * phase)).transpose(1, 2).contiguous()


def make_simulator(effects=()) -> HandSimulator:
    return HandSimulator(effects)
