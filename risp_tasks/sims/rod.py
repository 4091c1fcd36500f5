"""Rod: a clamped–clamped elastic beam (hexahedral FEM, implicit Euler, adjoint backward).

Equations, units and defaults: docs/models/rod.md.  Summary:

* mesh: 12 × 3 × 2 nodes (11 × 2 × 1 trilinear hexahedra) on the undeformed box
  [−0.5, 0.5] × [−0.1, 0.1] × [REST_HEIGHT − 0.05, REST_HEIGHT + 0.05]; the 6 nodes of each end face are
  fixed, the 10 interior cross-sections sit exactly at the sensors SENSOR_X;
* material: stable Neo-Hookean (``_fem``), Young's modulus E = 10^log10_E Pa, Poisson's ratio 0.3,
  density 500 kg/m³ with a lumped mass matrix; gravity 9.81 m/s² along −z;
* action: a vertical force on the rod's centre, smoothly clamped to [−500, 500] N and shared equally by
  the 12 nodes of the two cross-sections next to x = 0;
* time stepping: implicit (backward) Euler, dt = 0.01 s, solved by Newton's method with a backtracking
  line search on the incremental potential; the optional ``rayleigh_damping`` effect adds
  C = α M + β K₀ (K₀: stiffness matrix at rest);
* backward: the implicit-function theorem.  With g(x⁺; x, v, θ) = 0 the step's equation, the adjoint
  λ = H⁻¹ ∂L/∂x⁺ (H = ∂g/∂x⁺, symmetric) gives ∂L/∂θ = −λᵀ ∂g/∂θ; one linear solve per step, no
  differentiation through Newton's iterations.

State (360) = positions [m] of the 60 free nodes (x, y, z each, node order i-major: (i, j, k) with
i = 1…10 along x, j = 0…2 along y, k = 0…1 along z), then their velocities [m/s] in the same order.
``to_env_state`` gives the centreline height at the 10 sensors (mean z of nodes (i, 1, 0) and (i, 1, 1)).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from risp_data.envs import rod as geometry
from risp_data.errors import RispError

from . import _fem
from ._smooth import smooth_clamp
from .base import Effect, Simulator, SimulatorSpec

# -- model constants (docs/models/rod.md §Geometry and discretisation) ------------------------------
DT = 0.01  # s
NODES = (12, 3, 2)  # along x, y, z
POISSON = 0.3
GRAVITY = 9.81  # m/s², along −z
FORCE_LIMIT = 500.0  # N, |centre force| (smooth clamp)
FORCE_WIDTH = 1.0  # N, corner width of the smooth clamp
LOG10_E_RANGE = (3.0, 8.0)  # accepted log10 E (validity bounds; the identification range [4, 7] lies inside)
LOG10_E_TYPICAL = (4.0, 7.0)  # plausible range of log10 E (the paper's identification range)
NEWTON_MAX_ITERATIONS = 30
LINE_SEARCH_ABOVE = 1e-3  # m: Newton updates larger than this are line-searched
CHORD_BELOW = 1e-4  # m: after an update this small the next one reuses the factorisation
NEWTON_TOLERANCE = {torch.float64: 1e-10, torch.float32: 2e-6}  # m, max |Newton update| at convergence

NX, NY, NZ = NODES
NODES_PER_SECTION = NY * NZ
N_FREE_NODES = (NX - 2) * NODES_PER_SECTION
N_DOF = 3 * N_FREE_NODES  # 180

EFFECTS = {
    "rayleigh_damping": Effect(
        "rayleigh_damping", ("alpha", "beta"), (1.0, 0.01), ((0.0, 10.0), (0.0, 0.1)),
        "damping force −(α M + β K₀) v: α [1/s] mass-proportional, β [s] stiffness-proportional (K₀ at rest)",
        bounds=((0.0, math.inf), (0.0, math.inf)), units=("1/s", "s"),
    ),
}


def _state_names() -> tuple[str, ...]:
    nodes = [f"n{i}_{j}_{k}" for i in range(1, NX - 1) for j in range(NY) for k in range(NZ)]
    pos = [f"{n}.{c}" for n in nodes for c in "xyz"]
    vel = [f"{n}.v{c}" for n in nodes for c in "xyz"]
    return tuple(pos + vel)


SPEC = SimulatorSpec(
    env="rod",
    dt=DT,
    state_names=_state_names(),
    base_param_names=("log10_E",),
    base_param_defaults=(5.0,),
    action_dim=1,
    available_effects=EFFECTS,
    base_param_bounds=(LOG10_E_RANGE,),
    base_param_ranges=(LOG10_E_TYPICAL,),
    base_param_units=("log10 Pa",),
)


class _Model:
    """Per-dtype constant tables of the rod (docs/models/rod.md, "Discretisation")."""

    def __init__(self, dtype: torch.dtype):
        spacing = (geometry.ROD_LENGTH / (NX - 1), geometry.ROD_WIDTH / (NY - 1), geometry.ROD_THICKNESS / (NZ - 1))
        origin = (-geometry.ROD_LENGTH / 2, -geometry.ROD_WIDTH / 2, geometry.REST_HEIGHT - geometry.ROD_THICKNESS / 2)
        self.dtype = dtype
        self.grid = _fem.build_grid(origin, spacing, NODES, dtype)
        s = NODES_PER_SECTION
        self.left = self.grid.rest[:s]  # fixed end faces (6, 3)
        self.right = self.grid.rest[-s:]
        self.rest = self.grid.rest[s:-s].reshape(-1)  # (180,) free positions at rest
        self.mass = (geometry.ROD_DENSITY * self.grid.node_volume[s:-s]).repeat_interleave(3)  # lumped, (180,)
        z = torch.zeros(N_FREE_NODES, 3, dtype=dtype)
        z[:, 2] = 1.0
        self.ez = z.reshape(-1)  # 1 on the z dofs
        self.gravity = -GRAVITY * self.mass * self.ez  # (180,) N
        # centre load: the two cross-sections next to x = 0 (i = 5, 6 -> free sections 4, 5), 12 nodes
        load = torch.zeros(N_FREE_NODES, 3, dtype=dtype)
        centre = [(NX - 2) // 2 - 1, (NX - 2) // 2]
        for sec in centre:
            load[sec * s:(sec + 1) * s, 2] = 1.0 / (len(centre) * s)
        self.load = load.reshape(-1)  # (180,), sums to 1 on z
        # sensors: centreline (j = 1, mid-thickness) of free sections 0..9 = mean z of nodes (i, 1, 0), (i, 1, 1)
        sensor = [[(sec * s + (NY // 2) * NZ + k) * 3 + 2 for k in range(NZ)] for sec in range(NX - 2)]
        self.sensor_index = torch.tensor(sensor, dtype=torch.long)  # (10, 2)
        # banded (LAPACK lower) storage of symmetric free-dof matrices: band[d, c] = H[c + d, c]
        self._build_band_tables()
        # K₀: stiffness at rest for E = 1 (Rayleigh damping), dense for products and banded for solves
        _, He = _fem.energy_gradient(self.grid, self.grid.rest[None], POISSON, hessian=True)
        self.k0 = self._free_block(_fem.assemble_dense(self.grid, He))[0]
        self.k0_band = self.band(He)[0]

    def full(self, x: torch.Tensor) -> torch.Tensor:
        """Free positions (B, 180) -> all nodes (B, 72, 3)."""
        B = x.shape[0]
        return torch.cat((self.left.expand(B, -1, -1), x.view(B, N_FREE_NODES, 3), self.right.expand(B, -1, -1)), 1)

    def _build_band_tables(self):
        """Index maps from the element Hessian terms into band storage of the free block."""
        first = 3 * NODES_PER_SECTION
        dofs = (self.grid.elements[:, :, None] * 3 + torch.arange(3)).reshape(-1, 24) - first  # free dof numbers
        E = dofs.shape[0]
        # rank-one term, order [e, (a, i), (b, k)]
        rows1 = dofs[:, :, None].expand(E, 24, 24).reshape(-1)
        cols1 = dofs[:, None, :].expand(E, 24, 24).reshape(-1)
        # cofactor term, order [e, a, b, i, k]: row dof 3a + i, column dof 3b + k
        d = dofs.view(E, 8, 3)
        rows2 = d[:, :, None, :, None].expand(E, 8, 8, 3, 3).reshape(-1)
        cols2 = d[:, None, :, None, :].expand(E, 8, 8, 3, 3).reshape(-1)
        # μ term: the constant element Laplacian, summed once into a band
        self.bandwidth = 0
        maps = []
        for rows, cols in ((rows1, cols1), (rows2, cols2)):
            valid = (rows >= 0) & (rows < N_DOF) & (cols >= 0) & (cols < N_DOF) & (rows >= cols)
            self.bandwidth = max(self.bandwidth, int((rows - cols)[valid].max()))
            maps.append((rows, cols, valid))
        self.band_maps = [
            (torch.nonzero(valid).flatten(), ((rows - cols) * N_DOF + cols)[valid]) for rows, cols, valid in maps
        ]
        lap = _fem.grid_laplacian(self.grid, self.dtype).expand(E, 24, 24).reshape(1, -1)
        src, dst = self.band_maps[0]
        self.laplacian_band = lap.new_zeros(1, (self.bandwidth + 1) * N_DOF).index_add_(1, dst, lap[:, src])

    def band(self, He: "_fem.ElementHessians") -> torch.Tensor:
        """Element Hessians -> the free block in LAPACK lower band storage (B, bandwidth + 1, 180)."""
        B = He.rank_one.shape[0]
        band = He.mu * self.laplacian_band.expand(B, -1).clone()
        for part, (src, dst) in zip((He.rank_one, He.cofactor), self.band_maps):
            band.index_add_(1, dst, part.reshape(B, -1)[:, src])
        return band.view(B, self.bandwidth + 1, N_DOF)

    @staticmethod
    def _free_block(H: torch.Tensor) -> torch.Tensor:
        a = 3 * NODES_PER_SECTION
        return H[:, a:-a, a:-a]

    def elastic(self, x: torch.Tensor, hessian: bool):
        """Ψ̂'s gradient (B, 180) and banded Hessian (B, bandwidth + 1, 180) or None at free positions x (E = 1)."""
        grad, He = _fem.energy_gradient(self.grid, self.full(x), POISSON, hessian=hessian)
        s = NODES_PER_SECTION
        grad = grad[:, s:-s].reshape(x.shape[0], -1)
        return grad, (None if He is None else self.band(He))

    def elastic_energy(self, x: torch.Tensor) -> torch.Tensor:
        return _fem.energy(self.grid, self.full(x), POISSON)


_MODELS: dict[torch.dtype, _Model] = {}


def _model(dtype: torch.dtype) -> _Model:
    if dtype not in _MODELS:
        _MODELS[dtype] = _Model(dtype)
    return _MODELS[dtype]


# -- the implicit step: residual, Hessian, Newton (docs/models/rod.md, "Time stepping") ------------------
class _StepProblem:
    """g(x) = M(x − x̂)/dt² + (αM + βE K₀)(x − xₙ)/dt + E ∇Ψ̂(x) − f_ext,  x̂ = xₙ + dt vₙ.

    ``inertia = False`` drops the first two terms: the static equilibrium E ∇Ψ̂(x) = f_ext.
    g is the gradient of the incremental potential Φ, used by the line search.
    """

    def __init__(self, model: _Model, x_n, v_n, E, alpha, beta, force, inertia: bool = True):
        self.m, self.inertia = model, inertia
        self.x_n, self.E, self.alpha, self.beta = x_n, E[:, None], alpha[:, None], beta[:, None]
        self.x_hat = None if x_n is None else x_n + DT * v_n
        self.f_ext = model.gravity + force[:, None] * model.load

    def _damping(self, dx):  # (αM + βE K₀) dx
        return self.alpha * self.m.mass * dx + self.beta * self.E * (dx @ self.m.k0)

    def residual(self, x, hessian: bool):
        grad, H = self.m.elastic(x, hessian)
        g = self.E * grad - self.f_ext
        if hessian:  # banded: row 0 of the band is the diagonal
            H = self.E[:, :, None] * H
        if self.inertia:
            g = g + self.m.mass * (x - self.x_hat) / DT**2 + self._damping(x - self.x_n) / DT
            if hessian:
                H[:, 0] += self.m.mass * (1.0 / DT**2 + self.alpha / DT)
                H = H + (self.beta * self.E / DT)[:, :, None] * self.m.k0_band
        return g, H

    def potential(self, x):
        phi = self.E[:, 0] * self.m.elastic_energy(x) - (self.f_ext * x).sum(-1)
        if self.inertia:
            d, dn = x - self.x_hat, x - self.x_n
            phi = phi + 0.5 * (self.m.mass * d * d).sum(-1) / DT**2 + 0.5 * (dn * self._damping(dn)).sum(-1) / DT
        return phi


def _factor(band: torch.Tensor, allow_shift: bool = True) -> tuple[list, list[float]]:
    """Banded Cholesky factors of symmetric positive definite H, given in LAPACK lower band storage
    (B, kd + 1, n): LAPACK ``?pbtrf`` through SciPy, one matrix per batch row, O(n kd²) instead of the
    dense O(n³).  Returns (factors, shifts).

    Where H is not positive definite (strongly compressed elements of the stable Neo-Hookean material
    can make it so) and ``allow_shift`` is true, a growing multiple of the mean diagonal is added and
    the shift used is reported in ``shifts`` (0.0 where none was needed).  That is harmless inside
    Newton's method (a shifted H still gives a descent direction, and convergence is judged on the
    unshifted residual), but it would make an adjoint solve wrong, so the backward pass calls this with
    ``allow_shift=False`` and gets a RispError instead of silently wrong gradients.
    """
    from scipy.linalg import lapack

    bands = band.detach().cpu().numpy()
    (pbtrf,) = lapack.get_lapack_funcs(("pbtrf",), (bands,))
    factors, shifts = [], []
    for b, ab in enumerate(bands):
        c, info = pbtrf(ab, lower=1)
        used = 0.0
        if info != 0 and not allow_shift:
            raise RispError(
                f"rod: the step Hessian of batch row {b} is not positive definite at the solution, so the "
                "adjoint (gradient) would be wrong; reduce the force or the time step, or raise log10_E"
            )
        shift = 1e-8
        while info != 0 and shift < 1e3:
            used = shift * float(np.abs(ab[0]).mean())
            shifted = ab.copy()
            shifted[0] += used
            c, info = pbtrf(shifted, lower=1)
            shift *= 10.0
        if info != 0:
            raise RispError("rod: the implicit step's linear system is singular (non-physical parameters?)")
        factors.append(c)
        shifts.append(used)
    return factors, shifts


def _solve(factors: list, r: torch.Tensor) -> torch.Tensor:
    """H⁻¹ r (B, n) from the factors of :func:`_factor` (LAPACK ``?pbtrs``)."""
    from scipy.linalg import lapack

    if not factors:
        return torch.zeros_like(r)
    rhs = r.detach().cpu().numpy()
    (pbtrs,) = lapack.get_lapack_funcs(("pbtrs",), (factors[0],))
    out = np.empty_like(rhs)
    for b, c in enumerate(factors):
        out[b], _ = pbtrs(c, rhs[b], lower=1)
    return torch.from_numpy(out).to(r)


def _newton(problem: _StepProblem, x0: torch.Tensor, what: str) -> torch.Tensor:
    """Minimise the incremental potential Φ by Newton's method.

    Updates larger than LINE_SEARCH_ABOVE are checked by Armijo backtracking on Φ; smaller ones are in
    Newton's quadratic region and taken whole.  After an update smaller than CHORD_BELOW the next
    update reuses the last factorisation (a chord step: gradient only, no new Hessian), which converges
    at once that close to the solution.
    """
    tol = NEWTON_TOLERANCE.get(x0.dtype, 1e-11)
    x = x0
    g, H = problem.residual(x, hessian=True)
    factors, _ = _factor(H)
    for _ in range(NEWTON_MAX_ITERATIONS):
        dx = -_solve(factors, g)
        size = dx.abs().amax(-1)
        if bool((size <= tol).all()):
            return x + dx
        if not bool(torch.isfinite(size).all()):
            break
        if bool((size > LINE_SEARCH_ABOVE).any()):
            phi = problem.potential(x)
            slope = (g * dx).sum(-1)
            t = torch.ones_like(size)
            for _ in range(20):
                phi_try = problem.potential(x + t[:, None] * dx)
                bad = (phi_try > phi + 1e-4 * t * slope) & (t * size > LINE_SEARCH_ABOVE)
                if not bool(bad.any()):
                    break
                t = torch.where(bad, 0.5 * t, t)
            dx = t[:, None] * dx
        x = x + dx
        if bool((size <= CHORD_BELOW).all()):
            g, _ = problem.residual(x, hessian=False)
        else:
            g, H = problem.residual(x, hessian=True)
            factors, _ = _factor(H)
    raise RispError(f"rod: Newton's method did not converge {what} (non-physical parameters or force?)")


class _ImplicitEulerStep(torch.autograd.Function):
    """x⁺ = argmin Φ  (g(x⁺) = 0); backward by the adjoint λ = H(x⁺)⁻¹ x̄⁺ (docs/models/rod.md, "Adjoint")."""

    @staticmethod
    def forward(ctx, x_n, v_n, E, alpha, beta, force, model):
        with torch.no_grad():
            problem = _StepProblem(model, x_n, v_n, E, alpha, beta, force)
            x = _newton(problem, x_n + DT * v_n, "in a time step")
        ctx.model = model
        ctx.save_for_backward(x, x_n, v_n, E, alpha, beta, force)
        return x

    @staticmethod
    def backward(ctx, x_bar):
        x, x_n, v_n, E, alpha, beta, force = ctx.saved_tensors
        m = ctx.model
        with torch.no_grad():
            problem = _StepProblem(m, x_n, v_n, E, alpha, beta, force)
            _, H = problem.residual(x, hessian=True)
            factors, _ = _factor(H, allow_shift=False)  # a shifted H would give wrong gradients: raise
            lam = _solve(factors, x_bar)  # H symmetric: Hᵀ λ = x̄
            grad_unit, _ = m.elastic(x, hessian=False)
            dx = x - x_n
            m_lam = m.mass * lam
            k0_lam = lam @ m.k0
            # ∂L/∂p = −λᵀ ∂g/∂p for each input p of g
            g_xn = m_lam / DT**2 + (alpha[:, None] * m_lam + (beta * E)[:, None] * k0_lam) / DT
            g_vn = m_lam / DT
            g_E = -((lam * grad_unit).sum(-1) + beta / DT * (k0_lam * dx).sum(-1))
            g_alpha = -(m_lam * dx).sum(-1) / DT
            g_beta = -E * (k0_lam * dx).sum(-1) / DT
            g_force = (lam * m.load).sum(-1)
        return g_xn, g_vn, g_E, g_alpha, g_beta, g_force, None


class RodSimulator(Simulator):
    """Clamped–clamped elastic rod; see the module docstring and docs/models/rod.md."""

    spec = SPEC

    def _coefficients(self, params):
        E = 10.0 ** params[:, 0]
        if "rayleigh_damping" in self.effects:
            alpha = params[:, self.param_index("rayleigh_damping.alpha")]
            beta = params[:, self.param_index("rayleigh_damping.beta")]
        else:
            alpha = beta = torch.zeros_like(E)
        return E, alpha, beta

    @staticmethod
    def centre_force(actions: torch.Tensor) -> torch.Tensor:
        """Commanded force [N] -> applied force, smoothly clamped to [−500, 500] (width 1 N)."""
        return smooth_clamp(actions, -FORCE_LIMIT, FORCE_LIMIT, FORCE_WIDTH)

    def check_state(self, s0: torch.Tensor) -> None:
        # shapes, NaNs, dtypes and parameter bounds are checked by Simulator.check_inputs
        if s0.dtype not in (torch.float32, torch.float64):
            raise RispError(f"s0: the rod simulator runs in float32 or float64, got {s0.dtype}")

    def step(self, params, state, action, t):
        model = _model(state.dtype)
        E, alpha, beta = self._coefficients(params)
        x_n, v_n = state[:, :N_DOF], state[:, N_DOF:]
        x = _ImplicitEulerStep.apply(x_n, v_n, E, alpha, beta, self.centre_force(action[:, 0]), model)
        return torch.cat((x, (x - x_n) / DT), -1)

    def rollout(self, params, s0, actions, steps):
        """Integrate ``steps`` implicit Euler steps; returns (B, steps + 1, 360), row 0 = s0."""
        self.check_inputs(params, s0, actions, steps)
        if s0.shape[0] == 0:  # empty batch: nothing to solve
            return s0.new_zeros(0, steps + 1, s0.shape[1])
        model = _model(s0.dtype)
        E, alpha, beta = self._coefficients(params)
        force = self.centre_force(actions[:, :steps, 0])
        x, v = s0[:, :N_DOF], s0[:, N_DOF:]
        xs, vs = [x], [v]
        for t in range(steps):
            x_next = _ImplicitEulerStep.apply(x, v, E, alpha, beta, force[:, t], model)
            v = (x_next - x) / DT
            x = x_next
            xs.append(x)
            vs.append(v)
        return torch.cat((torch.stack(xs, 1), torch.stack(vs, 1)), -1)

    def to_env_state(self, states: torch.Tensor) -> torch.Tensor:
        """Full states (..., 360) -> centreline height [m] at the 10 sensors (..., 10)."""
        self.check_full_states(states)
        idx = _model(states.dtype).sensor_index
        return states[..., idx].mean(-1)

    def default_state(self, batch: int = 1, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """The undeformed rod at rest (no gravity sag): (batch, 360)."""
        rest = _model(dtype).rest
        return torch.cat((rest, torch.zeros_like(rest))).expand(batch, -1).clone()

    def rest_state(self, batch: int = 1, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Alias of :meth:`default_state` (kept for existing callers)."""
        return self.default_state(batch, dtype)

    def equilibrium_state(self, params: torch.Tensor, force: torch.Tensor | float = 0.0) -> torch.Tensor:
        """Static equilibrium under gravity and a constant centre force [N]: (B, 360), zero velocity.

        Solves E ∇Ψ̂(x) = f_gravity + f_centre by Newton's method from the undeformed rod (not
        differentiable; use it to start rollouts from the sagged rod).
        """
        s0 = self.rest_state(params.shape[0], params.dtype)
        force = torch.as_tensor(force, dtype=params.dtype).expand(params.shape[0], 1, 1)
        self.check_inputs(params, s0, force, 0)
        model = _model(params.dtype)
        with torch.no_grad():
            E, alpha, beta = self._coefficients(params.detach())
            problem = _StepProblem(model, None, None, E, alpha, beta, self.centre_force(force[:, 0, 0]), inertia=False)
            x = _newton(problem, model.rest.expand(params.shape[0], -1), "for the static equilibrium")
        return torch.cat((x, torch.zeros_like(x)), -1)


def beam_theory_sag(log10_E: float) -> float:
    """Euler–Bernoulli clamped–clamped beam under its own weight: w_max = q L⁴ / (384 E I) [m]."""
    E = 10.0**log10_E
    area = geometry.ROD_WIDTH * geometry.ROD_THICKNESS
    second_moment = geometry.ROD_WIDTH * geometry.ROD_THICKNESS**3 / 12.0
    q = geometry.ROD_DENSITY * area * GRAVITY
    return q * geometry.ROD_LENGTH**4 / (384.0 * E * second_moment)


def make_simulator(effects=()) -> RodSimulator:
    return RodSimulator(effects)


__all__ = ["RodSimulator", "SPEC", "beam_theory_sag", "make_simulator"]
