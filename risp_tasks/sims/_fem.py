"""Trilinear hexahedral finite elements with the stable Neo-Hookean energy (docs/models/rod.md).

A regular box grid of ``nx × ny × nz`` nodes; every element is the same axis-aligned box, so the shape
function gradients at the 2×2×2 Gauss points are one constant table G (8 points, 8 nodes, 3).

Energy density (Smith, de Goes, Kim 2018, "Stable Neo-Hookean Flesh Simulation", without the log term):

    Ψ(F) = μ/2 (‖F‖² − 3) + λ/2 (J − α)² − μ²/(2λ),   J = det F,   α = 1 + μ/λ,

rest-stable (P(I) = 0), defined for inverted elements, and a polynomial in the nodal positions; the
constant −μ²/(2λ) = −λ/2 (1 − α)² makes Ψ(I) = 0 (it changes no force or stiffness).  Here
everything is evaluated for unit Young's modulus (μ̂, λ̂ from E = 1 and Poisson's ratio ν): the
physical energy is E · Ψ̂, so the elastic forces and the tangent stiffness are linear in E.

    P̂ = ∂Ψ̂/∂F = μ̂ F + λ̂ (J − α) cof F
    ∂²Ψ̂/∂F_ij∂F_kl = μ̂ δ_ik δ_jl + λ̂ cof_ij cof_kl + λ̂ (J − α) ε_ikm ε_jln F_mn

All functions here are plain tensor code without autograd bookkeeping; the rod simulator calls them
inside ``torch.no_grad`` (forward Newton solve) or uses them in its hand-written adjoint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch


@dataclass(frozen=True)
class HexGrid:
    """Constant tables of a regular hexahedral grid (built once per dtype)."""

    rest: torch.Tensor  # (N, 3) rest positions of all nodes
    elements: torch.Tensor  # (E, 8) node indices, local order (di, dj, dk) ∈ {0,1}³ with dk fastest
    G: torch.Tensor  # (8 Gauss points, 8 local nodes, 3) ∂N_a/∂X at the Gauss points
    point_volume: float  # volume weight of one Gauss point (element volume / 8)
    node_volume: torch.Tensor  # (N,) lumped volume per node (each element gives 1/8 of its volume)
    hessian_index: torch.Tensor  # (E·24·24,) flat index into an (N·3)² matrix
    # constant tables of the element Hessian (see _element_hessians), computed once in build_grid and
    # stored here so they can never be confused with another grid's (no cache keyed by object id)
    laplacian: torch.Tensor  # (24, 24) Σ_q v ∇N_a·∇N_b δ_ik
    cross_table: torch.Tensor  # (24, 64) W[(q, n), (a, b)] = (∇N_a × ∇N_b)_n at Gauss point q
    levi_civita: torch.Tensor  # (9, 3) ε_ikm reshaped to [(i, k), m]


def node_id(i: int, j: int, k: int, ny: int, nz: int) -> int:
    return (i * ny + j) * nz + k


def build_grid(origin, spacing, counts, dtype: torch.dtype) -> HexGrid:
    """Grid with ``counts = (nx, ny, nz)`` nodes, node (i, j, k) at origin + (i, j, k) · spacing."""
    nx, ny, nz = counts
    hx, hy, hz = spacing
    rest = torch.tensor(
        [[origin[0] + i * hx, origin[1] + j * hy, origin[2] + k * hz]
         for i in range(nx) for j in range(ny) for k in range(nz)],
        dtype=dtype,
    )
    corners = [(di, dj, dk) for di in (0, 1) for dj in (0, 1) for dk in (0, 1)]
    elements = torch.tensor(
        [[node_id(i + di, j + dj, k + dk, ny, nz) for di, dj, dk in corners]
         for i in range(nx - 1) for j in range(ny - 1) for k in range(nz - 1)],
        dtype=torch.long,
    )
    g = 1.0 / math.sqrt(3.0)
    points = [(a * g, b * g, c * g) for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]
    G = torch.zeros(8, 8, 3, dtype=torch.float64)
    for q, (xi, eta, zeta) in enumerate(points):
        for a, (di, dj, dk) in enumerate(corners):
            sa, sb, sc = 2 * di - 1, 2 * dj - 1, 2 * dk - 1
            G[q, a, 0] = sa * (1 + sb * eta) * (1 + sc * zeta) / 8 * (2 / hx)
            G[q, a, 1] = sb * (1 + sa * xi) * (1 + sc * zeta) / 8 * (2 / hy)
            G[q, a, 2] = sc * (1 + sa * xi) * (1 + sb * eta) / 8 * (2 / hz)
    volume = hx * hy * hz
    n_nodes = nx * ny * nz
    node_volume = torch.zeros(n_nodes, dtype=torch.float64)
    node_volume.index_add_(0, elements.flatten(), torch.full((elements.numel(),), volume / 8, dtype=torch.float64))
    dofs = (elements[:, :, None] * 3 + torch.arange(3)).reshape(-1, 24)  # (E, 24)
    hessian_index = (dofs[:, :, None] * (n_nodes * 3) + dofs[:, None, :]).flatten()
    laplacian, W, eps9 = _hessian_tables(G, volume / 8)
    return HexGrid(rest, elements, G.to(dtype), volume / 8, node_volume.to(dtype), hessian_index,
                   laplacian.to(dtype), W.to(dtype), eps9.to(dtype))


def lame_unit(nu: float) -> tuple[float, float, float]:
    """μ̂, λ̂ for E = 1 and the stable Neo-Hookean rest offset α = 1 + μ/λ."""
    mu = 1.0 / (2.0 * (1.0 + nu))
    lam = nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam, 1.0 + mu / lam


def deformation_gradients(grid: HexGrid, x: torch.Tensor) -> torch.Tensor:
    """All nodal positions x (B, N, 3) -> F (B, E, 8, 3, 3), F_ij = Σ_a x_ai ∂N_a/∂X_j."""
    xe = x[:, grid.elements]  # (B, E, 8, 3)
    return torch.einsum("zeai,qaj->zeqij", xe, grid.G)


def _cofactor(F: torch.Tensor) -> torch.Tensor:
    """cof F: column j is f_{j+1} × f_{j+2} (f_j = column j of F) = ∂ det F / ∂F."""
    Ft = F.transpose(-1, -2)  # rows are the columns of F
    rows = torch.linalg.cross(Ft.roll(-1, dims=-2), Ft.roll(-2, dims=-2), dim=-1)
    return rows.transpose(-1, -2)


def energy(grid: HexGrid, x: torch.Tensor, nu: float) -> torch.Tensor:
    """Ψ̂ summed over the Gauss points of every element, per batch row: (B,)."""
    mu, lam, alpha = lame_unit(nu)
    F = deformation_gradients(grid, x)
    J = torch.linalg.det(F)
    psi = 0.5 * mu * ((F * F).sum((-1, -2)) - 3.0) + 0.5 * lam * (J - alpha) ** 2 - 0.5 * mu * mu / lam  # Ψ(I) = 0
    return psi.sum((-1, -2)) * grid.point_volume


class ElementHessians(NamedTuple):
    """The three terms of the element Hessians ∂²Ψ̂/∂x_e² (see :func:`_element_hessians`).

    ``rank_one`` (B, E, 24, 24) is indexed [(a, i), (b, k)] (element dof 3a + i); ``cofactor``
    (B, E, 8, 8, 3, 3) is indexed [a, b, i, k] (kept in the order it is computed in, so that assembly
    gathers from it without a transposed copy); ``mu`` multiplies the constant ``grid_laplacian``.
    """

    rank_one: torch.Tensor
    cofactor: torch.Tensor
    mu: float

    def full(self, grid: "HexGrid") -> torch.Tensor:
        """(B, E, 24, 24) = all three terms in [(a, i), (b, k)] order."""
        B, E = self.rank_one.shape[:2]
        j = self.cofactor.permute(0, 1, 2, 4, 3, 5).reshape(B, E, 24, 24)
        return self.rank_one + j + self.mu * grid_laplacian(grid, self.rank_one.dtype)


def energy_gradient(grid: HexGrid, x: torch.Tensor, nu: float, hessian: bool = False):
    """∂Ψ̂/∂x (B, N, 3) and, when asked, the element Hessians as :class:`ElementHessians`."""
    mu, lam, alpha = lame_unit(nu)
    B = x.shape[0]
    F = deformation_gradients(grid, x)
    C = _cofactor(F)
    J = (F[..., :, 0] * C[..., :, 0]).sum(-1)  # det F = f_0 · (f_1 × f_2)
    s = lam * (J - alpha)
    P = mu * F + s[..., None, None] * C  # (B, E, 8, 3, 3)
    ge = torch.einsum("qaj,zeqij->zeai", grid.G, P) * grid.point_volume  # (B, E, 8, 3)
    grad = torch.zeros_like(x).index_add_(1, grid.elements.flatten(), ge.reshape(B, -1, 3))
    if not hessian:
        return grad, None
    return grad, _element_hessians(grid, F, C, s, mu, lam)


def _element_hessians(grid: HexGrid, F, C, s, mu: float, lam: float) -> ElementHessians:
    """He = Σ_q v B_qᵀ 𝔸_q B_q for 𝔸 = μ I + λ vec(C) vec(C)ᵀ + λ(J − α) ∂²J/∂F², term by term:

    * μ term: μ δ_ik Σ_q v ∇N_a·∇N_b, a constant (the element Laplacian ⊗ I₃);
    * λ term: λ v Σ_q u_q u_qᵀ with u_q[a, i] = Σ_j ∂N_a/∂X_j C_ij (rank one per Gauss point);
    * J term: Σ_jl ε_jln ∂N_a/∂X_j ∂N_b/∂X_l = (∇N_a × ∇N_b)_n =: w_q[a, b, n], so
      He[a i, b k] = Σ_m ε_ikm R[m, a, b] with R[m, a, b] = Σ_q v s_q Σ_n F_mn w_q[a, b, n].
    """
    W, eps9 = grid.cross_table.to(F.dtype), grid.levi_civita.to(F.dtype)
    B, E = F.shape[0], F.shape[1]
    v = grid.point_volume
    u = torch.einsum("qaj,zeqij->zeqai", grid.G, C).reshape(B, E, 8, 24)  # (B, E, q, (a, i))
    rank_one = (lam * v) * (u.transpose(-1, -2) @ u)
    SF = (v * s)[..., None, None] * F  # (B, E, q, m, n)
    R = SF.permute(0, 1, 3, 2, 4).reshape(B * E * 3, 24) @ W  # ((B, E, m), (a, b)): one GEMM
    R = R.view(B, E, 3, 64).transpose(-1, -2).reshape(B * E * 64, 3)
    cofactor = (R @ eps9.T).view(B, E, 8, 8, 3, 3)  # [a, b, i, k]
    return ElementHessians(rank_one, cofactor, mu)


def grid_laplacian(grid: HexGrid, dtype: torch.dtype) -> torch.Tensor:
    """(24, 24): Σ_q v ∇N_a·∇N_b δ_ik, the μ term of every element Hessian (stored on the grid)."""
    return grid.laplacian.to(dtype)


def _hessian_tables(G: torch.Tensor, point_volume: float):
    """float64 (laplacian (24, 24), W (24, 64), ε (9, 3)) from the shape-function gradients G (8, 8, 3)."""
    lap = torch.einsum("qaj,qbj->ab", G, G) * point_volume
    laplacian = torch.kron(lap, torch.eye(3, dtype=torch.float64))
    w = torch.linalg.cross(G[:, :, None, :].expand(8, 8, 8, 3), G[:, None, :, :].expand(8, 8, 8, 3), dim=-1)
    W = w.permute(0, 3, 1, 2).reshape(24, 64)  # [(q, n), (a, b)]
    eps = torch.zeros(3, 3, 3, dtype=torch.float64)
    for (i, j, k), val in {(0, 1, 2): 1, (1, 2, 0): 1, (2, 0, 1): 1, (0, 2, 1): -1, (2, 1, 0): -1, (1, 0, 2): -1}.items():
        eps[i, j, k] = val
    return laplacian, W, eps.reshape(9, 3)


def assemble_dense(grid: HexGrid, He: ElementHessians) -> torch.Tensor:
    """Element Hessians -> global (B, 3N, 3N)."""
    full = He.full(grid)
    B, n = full.shape[0], 3 * grid.rest.shape[0]
    H = full.new_zeros(B, n * n).index_add_(1, grid.hessian_index, full.reshape(B, -1))
    return H.view(B, n, n)
