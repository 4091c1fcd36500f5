"""Cube: a rigid cube with penalty contact against the floor z = 0 at its 8 corners (docs/models.md §3).

Full state (13), SI units, the layout of the real tosses in data/cube-tosses:

    x y z        centre of the cube, world frame [m]
    qw qx qy qz  orientation, unit quaternion, body to world (renormalized every substep)
    vx vy vz     linear velocity, world frame [m/s]
    wx wy wz     angular velocity, body frame [rad/s]

No control input.  Parameters: λ = log10 k_n (normal stiffness, N/m per corner) and the normal damping
d_n (N·s/m per corner), plus those of the enabled effects.  Side length and mass are constructor
options (defaults CUBE_SIDE, CUBE_MASS of risp_data.envs.cube; the real cube: side=0.1048, mass=0.37).
Integrator: linearly implicit Euler on (v, ω) with ``substeps`` substeps per step of dt (docs §3.4),
contact, friction and rolling friction all linearized into one 6 × 6 solve per substep.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from risp_data.envs.cube import CUBE_MASS, CUBE_SIDE
from risp_data.errors import RispError

from ._rigid import (
    check_unit_quaternion_state,
    GRAVITY,
    const,
    normalize_quat,
    quat_mul_pure_left,
    quat_outer,
    rigid_to_env_state,
    rotation_form,
    rotation_matrix,
)
from .base import Effect, Simulator, SimulatorSpec

DT = 0.01  # s, one step of the rollout
SUBSTEPS = 2  # linearly implicit substeps per step (h = dt / substeps)
CONTACT_WIDTH = 1e-6  # m: δ, the softplus rounding of the penetration
_CLAMP = 30.0  # smooth-function arguments are clamped at −30 (σ(−30) ≈ 1e-13)
FLOOR_WIDTH = 0.1  # N: rounding width of the zero floor of the normal force (sharper: rougher fits)
FRICTION_EPS = 1e-2  # m/s: ε of the smoothed Coulomb law
ROLLING_EPS = 0.1  # rad/s: ε_ω of the smoothed rolling-friction direction
LOG10_KN = 6.0  # ground truth of the identification task, range [5.5, 6.5)
DN = 100.0  # N·s/m per corner: damping ratio ≈ 0.1 for the default cube (1 kg) resting on a face

STATE_NAMES = ("x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz")
_INF = float("inf")

EFFECTS = {
    "friction": Effect(
        "friction", ("mu",), (0.3,), ((0.0, 1.0),),
        "smoothed Coulomb friction f_t = −mu·φ(f_n⁺)·v_t / sqrt(|v_t|² + ε²) at each corner (f_n⁺: the normal force "
        "the substep will apply, smoothly floored: φ; docs/models.md §3.3)",
        bounds=((0.0, _INF),), units=("1",)),
    "restitution": Effect(
        "restitution", ("alpha",), (0.5,), ((0.0, 2.0),),
        "Hunt–Crossley contact damping: extra normal force alpha·f_k·(penetration rate); "
        "coefficient of restitution e ≈ 1 − (2/3)·alpha·v_impact",
        bounds=((0.0, _INF),), units=("s/m",)),
    "rolling_friction": Effect(
        "rolling_friction", ("mu_r",), (0.002,), ((0.0, 0.01),),
        "torque −mu_r·(Σ φ(f_n⁺))·ω / sqrt(|ω|² + ε_ω²) opposing the rotation while in contact",
        bounds=((0.0, _INF),), units=("m",)),
}

SPEC = SimulatorSpec(
    env="cube",
    dt=DT,
    state_names=STATE_NAMES,
    base_param_names=("log10_kn", "dn"),
    base_param_defaults=(LOG10_KN, DN),
    action_dim=0,
    available_effects=EFFECTS,
    base_param_bounds=((2.0, 9.0), (0.0, _INF)),
    base_param_ranges=((5.5, 6.5), (0.0, 300.0)),
    base_param_units=("log10(N/m)", "N s/m"),
)


def rest_penetration(mass: float, k_n: float, n: int = 4, width: float = CONTACT_WIDTH) -> float:
    """Static penetration of ``n`` corners carrying m·g (docs §3.2): φ(f_k) = m g / n with
    f_k = k_n·δ·sp(d/δ) and φ(y) = y·σ(y/w), i.e. d = δ·log(expm1(f_k / (k_n δ)));
    → m g / (n k_n) when that is ≫ δ and m g / n ≫ w."""
    load = mass * GRAVITY / n
    f_k = load
    for _ in range(60):  # Newton on φ(f_k) = load (φ is increasing for f_k > 0)
        s = 1.0 / (1.0 + math.exp(-f_k / FLOOR_WIDTH))
        f_k -= (f_k * s - load) / (s + f_k / FLOOR_WIDTH * s * (1.0 - s))
    x = f_k / (k_n * width)
    return width * (x + math.log(-math.expm1(-x)))  # log(e^x − 1), stable for large x


@dataclass(frozen=True)
class _Consts:
    """Per-rollout tensors derived from params and the geometry."""

    h: float
    width: float
    mass: float
    k: torch.Tensor  # (B, 1) k_n = 10^λ
    k_delta: torch.Tensor  # (B, 1) k_n·δ
    h_k: torch.Tensor  # (B, 1) h·k_n
    dn: torch.Tensor  # (B, 1)
    M: torch.Tensor  # (B, 6, 6) generalized mass diag(m, m, m, I, I, I)
    gravity: torch.Tensor  # (6,) generalized gravity force (0, 0, −m g, 0, 0, 0)
    corner_form: torch.Tensor  # (16, 24): R(q) b_c = vec(q qᵀ) @ corner_form
    corner_z_form: torch.Tensor  # (16, 56): (r_c,z for the 8 corners, then j_z,c − (e_z, 0)) from vec(q qᵀ)
    jac: torch.Tensor  # (3, 18): J_c = r_c @ jac + jac_offset (3 × 6 per corner)
    jac_offset: torch.Tensor  # (18,)
    jac_z: torch.Tensor  # (3, 6): the z row only
    jac_z_offset: torch.Tensor  # (6,)
    eye3: torch.Tensor  # (3, 3)
    mu: torch.Tensor | None
    alpha: torch.Tensor | None
    mu_r: torch.Tensor | None


class CubeSimulator(Simulator):
    """Differentiable cube with penalty floor contact (docs/models.md §3).

    Options: ``side`` [m], ``mass`` [kg], ``dt`` [s], ``substeps`` (h = dt/substeps), ``contact_width``
    δ [m].  The defaults are fast and stable (stress-tested over the parameter ranges); the implicit step
    dissipates energy at impacts it does not resolve (docs §3.4): use more substeps when bounce heights
    matter.
    """

    def __init__(self, effects: tuple[str, ...] | list[str] = (), *, side: float = CUBE_SIDE,
                 mass: float = CUBE_MASS, dt: float = DT, substeps: int = SUBSTEPS,
                 contact_width: float = CONTACT_WIDTH):
        for name, value in (("side", side), ("mass", mass), ("dt", dt), ("contact_width", contact_width)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise RispError(f"{name} must be a positive number, got {value!r}")
        if not isinstance(substeps, int) or substeps < 1:
            raise RispError(f"substeps must be a positive int, got {substeps!r}")
        self.spec = dataclasses.replace(SPEC, dt=float(dt))
        super().__init__(effects)
        self.side, self.mass, self.substeps, self.contact_width = float(side), float(mass), substeps, float(contact_width)

    @property
    def inertia(self) -> float:
        """I = m·s²/6 about every axis through the centre (solid cube): no gyroscopic torque."""
        return self.mass * self.side**2 / 6

    # -- layout ---------------------------------------------------------------------------------
    def default_state(self, batch: int = 1, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Resting flat on the floor (centre at z = side/2), at rest."""
        s = [0.0, 0.0, self.side / 2, 1.0, 0.0, 0.0, 0.0] + [0.0] * 6
        return torch.tensor(s, dtype=dtype).expand(batch, -1).clone()

    def check_state(self, s0: torch.Tensor) -> None:
        check_unit_quaternion_state(s0)

    def to_env_state(self, states: torch.Tensor) -> torch.Tensor:
        """(..., 13) -> (..., 6) = (x, y, z, yaw, pitch, roll) of risp_data's cube environment."""
        return rigid_to_env_state(states)

    # -- dynamics -------------------------------------------------------------------------------
    def _consts(self, params: torch.Tensor) -> _Consts:
        like = dict(dtype=params.dtype, device=params.device)
        B = params.shape[0]
        I = self.inertia
        M = torch.diag(torch.tensor([self.mass] * 3 + [I] * 3, **like)).expand(B, 6, 6)
        half = self.side / 2
        corners = torch.tensor(list(itertools.product((-half, half), repeat=3)), **like)
        jac, jac_offset = const("corner_jacobian", params), const("corner_jacobian_offset", params).flatten()
        jac_z = jac.view(3, 3, 6)[:, 2]  # (3, 6): the z row of J_c as a linear map of r_c
        form = rotation_form(corners)

        def eff(name):
            return self.effect_params(params, name)

        k = torch.pow(10.0, params[:, 0:1])

        return _Consts(
            h=self.dt / self.substeps,
            width=self.contact_width,
            mass=self.mass,
            k=k,
            k_delta=k * self.contact_width,
            h_k=k * (self.dt / self.substeps),
            dn=params[:, 1:2],
            M=M,
            gravity=torch.tensor([0.0, 0.0, -self.mass * GRAVITY, 0.0, 0.0, 0.0], **like),
            corner_form=form,
            corner_z_form=torch.cat([form.view(16, 8, 3)[..., 2], (form.view(16, 8, 3) @ jac_z).flatten(1)], 1),
            jac=jac,
            jac_offset=jac_offset,
            jac_z=jac_z,
            jac_z_offset=jac_offset.view(3, 6)[2],
            eye3=torch.eye(3, **like),
            mu=eff("friction"),
            alpha=eff("restitution"),
            mu_r=eff("rolling_friction"),
        )

    @staticmethod
    def _substep(c: _Consts, p, q, u):
        """One linearly implicit Euler substep of length h (docs §3.4), u = (v, ω) with ω in the world frame.

        (M + h·Σ_c J_cᵀ G_c J_c) Δu = h·(Σ_c J_cᵀ f̃_c + F_ext),   J_c = [I, −[r_c]×] (corner velocity v + ω × r_c),

        G_c: the normal force's (negated) Jacobian w.r.t. the corner velocity plus h·(normal stiffness), and
        friction's lagged damping coefficient C = μ φ(f_n⁺)/s on the tangential axes;
        f̃_c: the corner force with its normal part extrapolated by h·k_n·σ·(penetration rate).
        """
        h, delta = c.h, c.width
        B = p.shape[0]
        qq = quat_outer(q)
        if c.mu is None:  # one product gives the corner heights r_c,z and the Jacobian rows j_z,c
            rz_jz = qq @ c.corner_z_form  # (B, 8 + 48)
            r_z, Jz = rz_jz[:, :8], rz_jz[:, 8:].view(B, 8, 6) + c.jac_z_offset
        else:
            r = (qq @ c.corner_form).unflatten(-1, (8, 3))  # (B, 8, 3) corner offsets R b_c, world
            r_z = r[..., 2]
        pen = -(p[:, 2:3] + r_z)  # (B, 8) penetration depth d_c = −z_c

        # Normal force (docs §3.2): f_n = φ_w(f_k + (d_n σ + α f_k)·ḋ), f_k = k δ sp(d/δ), σ = σ(d/δ):
        # elastic + damping, smoothly floored at zero by φ_w(x) = x·σ(x/w), w = FLOOR_WIDTH (pushes, hardly pulls).
        # (clamped at −30 δ: beyond it the contact terms are < 1e-13 of their scale, and letting them run on
        # into subnormal numbers makes the small matrix products 100× slower)
        x = (pen / delta).clamp(min=-_CLAMP)
        sig = torch.sigmoid(x)
        f_k = c.k_delta * F.softplus(x, threshold=40.0)
        damp = c.dn * sig
        if c.alpha is not None:
            damp = damp + c.alpha * f_k

        def normal_force(pen_rate):
            f_n, gate = _floor(f_k + damp * pen_rate)
            g_k = gate * (c.h_k * sig)  # h·(stiffness)
            g_n = gate * damp + g_k  # damping + h·stiffness: the implicit weight of the corner
            stiff_rate = g_k * pen_rate
            return f_n, g_n, f_n + stiff_rate  # last: f_n extrapolated by h·(stiffness)·ḋ

        if c.mu is None:
            pen_rate = -(Jz @ u.unsqueeze(-1)).squeeze(-1)
            f_n, g_n, f_ext = normal_force(pen_rate)
            JzT = Jz.transpose(1, 2)
            A = c.M + h * (JzT @ (g_n.unsqueeze(-1) * Jz))
            force = (JzT @ f_ext.unsqueeze(-1)).squeeze(-1)
        else:
            # Smoothed Coulomb friction (docs §3.3): f_t = −μ f_n v_t / s, s = sqrt(|v_t|² + ε²).
            J = (r @ c.jac + c.jac_offset).view(B, 24, 6)  # rows j_x, j_y, j_z of every corner
            vc = (J @ u.unsqueeze(-1)).view(B, 8, 3)  # corner velocities v + ω × r
            vt = vc[..., :2]
            f_n, g_n, f_ext = normal_force(-vc[..., 2])
            s = torch.sqrt((vt * vt).sum(-1, keepdim=True) + FRICTION_EPS**2)  # (B, 8, 1)
            # A lagged implicit damper f_t = −C·v_t', C = μ φ(f_n⁺)/s (docs §3.4): backward Euler on a positive
            # damper only removes energy, whatever C is (the former explicit magnitude fed energy into tosses).
            Jz = J.view(B, 8, 3, 6)[:, :, 2]
            f_fr = _normal_predicted(c, Jz, g_n, f_ext)
            C = c.mu.unsqueeze(-1) * f_fr.unsqueeze(-1) / s  # (B, 8, 1)
            f = torch.cat([-C * vt, f_ext.unsqueeze(-1)], -1)  # (B, 8, 3)
            W = torch.cat([C, C, g_n.unsqueeze(-1)], -1).view(B, 24, 1)  # G_c = diag(C, C, g_n)
            JT = J.transpose(1, 2)
            A = c.M + h * (JT @ (W * J))
            force = (JT @ f.view(B, 24, 1)).squeeze(-1)
        force = force + c.gravity
        if c.mu_r is not None:
            # Rolling friction (docs §3.3): τ = −μ_r (Σ_c φ(f_n,c⁺)) ω / sqrt(|ω|² + ε_ω²), a lagged implicit
            # damper in ω like sliding friction.
            w = u[:, 3:]
            s_w = torch.sqrt((w * w).sum(1, keepdim=True) + ROLLING_EPS**2)
            # without sliding friction, A is still the normal-only matrix: the predictor reuses it
            f_rr = f_fr if c.mu is not None else _normal_predicted(c, Jz, g_n, f_ext, A_n=A)
            cr = c.mu_r * f_rr.sum(1, keepdim=True) / s_w  # (B, 1): a lagged implicit damper, as sliding friction
            force = force + F.pad(-cr * w, (3, 0))
            A = A + h * F.pad(cr.unsqueeze(-1) * c.eye3, (3, 0, 3, 0))
        u_new = u + torch.linalg.solve(A, h * force)
        p_new = p + h * u_new[:, :3]
        q_new = normalize_quat(q + (0.5 * h) * quat_mul_pure_left(u_new[:, 3:], q))
        return p_new, q_new, u_new

    def _advance(self, c: _Consts, p, q, v, w_body):
        """One step of dt = substeps·h; converts ω between the body (state) and world (substep) frames."""
        u = torch.cat([v, (rotation_matrix(q) @ w_body.unsqueeze(-1)).squeeze(-1)], 1)
        for _ in range(self.substeps):
            p, q, u = self._substep(c, p, q, u)
        w_body = (u[:, 3:].unsqueeze(1) @ rotation_matrix(q)).squeeze(1)  # Rᵀ ω
        return p, q, u[:, :3], w_body

    def step(self, params: torch.Tensor, state: torch.Tensor, action: torch.Tensor | None, t: int) -> torch.Tensor:
        c = self._consts(params)
        p, q, v, w = state[:, 0:3], normalize_quat(state[:, 3:7]), state[:, 7:10], state[:, 10:13]
        return torch.cat(self._advance(c, p, q, v, w), 1)

    def rollout(self, params: torch.Tensor, s0: torch.Tensor, actions: torch.Tensor | None, steps: int) -> torch.Tensor:
        """Same result as repeated :meth:`step`, with the per-rollout work hoisted out of the loop."""
        self.check_inputs(params, s0, actions, steps)
        c = self._consts(params)
        cur = (s0[:, 0:3], normalize_quat(s0[:, 3:7]), s0[:, 7:10], s0[:, 10:13])
        traj = []
        for _ in range(steps):
            cur = self._advance(c, *cur)
            traj.append(cur)
        if not traj:
            return s0.unsqueeze(1)
        later = torch.cat([torch.stack(parts, 1) for parts in zip(*traj)], -1)
        return torch.cat([s0.unsqueeze(1), later], 1)


def _normal_predicted(c: _Consts, Jz: torch.Tensor, g_n: torch.Tensor, f_ext: torch.Tensor,
                      A_n: torch.Tensor | None = None) -> torch.Tensor:
    """φ(f_n⁺) (B, 8): the normal forces the substep applies, by a normal-only solve (docs §3.4)

        A_n Δu_n = h (Σ_c j_z,cᵀ f̃_n,c + F_g),   A_n = M + h Σ_c g_n,c j_z,cᵀ j_z,c,   f_n⁺ = f̃_n − g_n·(J_z Δu_n)

    (A_n: pass it where the caller has built it). f̃_n alone overestimates the force ~50× at an unresolved
    impact, where the solve stops the corner.
    """
    JzT = Jz.transpose(1, 2)
    if A_n is None:
        A_n = c.M + c.h * (JzT @ (g_n.unsqueeze(-1) * Jz))
    du_n = torch.linalg.solve(A_n, c.h * ((JzT @ f_ext.unsqueeze(-1)).squeeze(-1) + c.gravity))
    return _floor(f_ext - g_n * (Jz @ du_n.unsqueeze(-1)).squeeze(-1))[0]


def _floor(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """φ(x) = x·σ(x/w), w = FLOOR_WIDTH: a smooth max(x, 0) that is exactly 0 at x = 0; and φ'(x)."""
    y = (x / FLOOR_WIDTH).clamp(min=-_CLAMP)  # no subnormal numbers (see _substep)
    sy = torch.sigmoid(y)
    return x * sy, sy * (1.0 + y * (1.0 - sy))


def make_simulator(effects: tuple[str, ...] = (), **options) -> CubeSimulator:
    """The cube simulator with the named effects; ``options``: side, mass, dt, substeps, contact_width."""
    return CubeSimulator(effects, **options)
