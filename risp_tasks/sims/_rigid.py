"""Quaternion and rigid-body helpers shared by the quadrotor and cube simulators (docs/models.md §1).

Quaternions are scalar-first (w, x, y, z), body to world, as in ``risp_data.envs.rotations``.  The
rotation matrix and the Hamilton product are written as bilinear forms with constant coefficient
tensors, so that each costs one small matmul instead of dozens of element-wise ops: the simulators
run a Python loop over time steps and their speed is set by the number of autograd nodes per step.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F

from risp_data.envs.rotations import quat_to_euler
from risp_data.errors import RispError

GRAVITY = 9.81  # m/s², along −z (world z is up)

_W, _X, _Y, _Z = range(4)


@functools.lru_cache(maxsize=None)
def _rotation_form_np() -> np.ndarray:
    """Q (16, 9): vec(R(q)) = vec(q qᵀ) @ Q for a unit quaternion q (homogeneous form of R)."""
    Q = np.zeros((4, 4, 3, 3))
    terms = {
        (0, 0): [(1, _W, _W), (1, _X, _X), (-1, _Y, _Y), (-1, _Z, _Z)],
        (1, 1): [(1, _W, _W), (-1, _X, _X), (1, _Y, _Y), (-1, _Z, _Z)],
        (2, 2): [(1, _W, _W), (-1, _X, _X), (-1, _Y, _Y), (1, _Z, _Z)],
        (0, 1): [(2, _X, _Y), (-2, _W, _Z)],
        (1, 0): [(2, _X, _Y), (2, _W, _Z)],
        (0, 2): [(2, _X, _Z), (2, _W, _Y)],
        (2, 0): [(2, _X, _Z), (-2, _W, _Y)],
        (1, 2): [(2, _Y, _Z), (-2, _W, _X)],
        (2, 1): [(2, _Y, _Z), (2, _W, _X)],
    }
    for (i, j), ts in terms.items():
        for c, a, b in ts:
            Q[a, b, i, j] += c
    return Q.reshape(16, 9)


@functools.lru_cache(maxsize=None)
def _hamilton_np() -> np.ndarray:
    """C (4, 4, 4): (p ⊗ q)_k = Σ_ij p_i q_j C[i, j, k] (Hamilton product, scalar first)."""
    C = np.zeros((4, 4, 4))
    table = [  # (i, j, k, sign): p_i q_j contributes sign to component k
        (0, 0, 0, 1), (1, 1, 0, -1), (2, 2, 0, -1), (3, 3, 0, -1),
        (0, 1, 1, 1), (1, 0, 1, 1), (2, 3, 1, 1), (3, 2, 1, -1),
        (0, 2, 2, 1), (1, 3, 2, -1), (2, 0, 2, 1), (3, 1, 2, 1),
        (0, 3, 3, 1), (1, 2, 3, 1), (2, 1, 3, -1), (3, 0, 3, 1),
    ]
    for i, j, k, s in table:
        C[i, j, k] = s
    return C


@functools.lru_cache(maxsize=None)
def _const(name: str, dtype: torch.dtype, device: str) -> torch.Tensor:
    if name == "R":
        a = _rotation_form_np()
    elif name == "R_col2":  # third column of R: the body z axis in world coordinates
        a = _rotation_form_np()[:, [2, 5, 8]]
    elif name == "R_row2":  # third row of R: world z of body-frame vectors
        a = _rotation_form_np()[:, [6, 7, 8]]
    elif name == "q_x_pure":  # q ⊗ (0, ω): rows indexed by (q_i, ω_j)
        a = _hamilton_np()[:, 1:, :].reshape(12, 4)
    elif name == "pure_x_q":  # (0, ω) ⊗ q: rows indexed by (ω_i, q_j)
        a = _hamilton_np()[1:, :, :].reshape(12, 4)
    elif name == "skew":  # [r]× = (r @ S).view(3, 3), so that [r]× u = r × u
        S = np.zeros((3, 3, 3))
        S[2, 0, 1], S[1, 0, 2] = -1, 1
        S[2, 1, 0], S[0, 1, 2] = 1, -1
        S[1, 2, 0], S[0, 2, 1] = -1, 1
        a = S.reshape(3, 9)
    elif name == "corner_jacobian":  # J_c = [I, −[r]×] = E + (r @ P).view(3, 6): rows j_x, j_y, j_z
        P = np.zeros((3, 3, 6))
        P[2, 0, 4], P[1, 0, 5] = 1, -1  # j_x = (1, 0, 0, 0, r_z, −r_y)
        P[2, 1, 3], P[0, 1, 5] = -1, 1  # j_y = (0, 1, 0, −r_z, 0, r_x)
        P[1, 2, 3], P[0, 2, 4] = 1, -1  # j_z = (0, 0, 1, r_y, −r_x, 0)
        a = P.reshape(3, 18)
    elif name == "corner_jacobian_offset":
        a = np.concatenate([np.eye(3), np.zeros((3, 3))], 1)
    else:  # pragma: no cover - programming error
        raise KeyError(name)
    return torch.tensor(a, dtype=dtype, device=device)


def const(name: str, like: torch.Tensor) -> torch.Tensor:
    """A cached constant tensor with the dtype and device of ``like``."""
    return _const(name, like.dtype, str(like.device))


def quat_outer(q: torch.Tensor) -> torch.Tensor:
    """(B, 4) -> (B, 16): the entries of q qᵀ, the input of the bilinear rotation forms."""
    return (q.unsqueeze(-1) * q.unsqueeze(-2)).flatten(-2)


def rotation_form(points: torch.Tensor) -> torch.Tensor:
    """(16, 3N) coefficients C with (R(q) b_n)_i = (vec(q qᵀ) @ C)[3n + i] for body points b (N, 3)."""
    Q = const("R", points).unflatten(-1, (3, 3))  # (16, 3, 3)
    return torch.einsum("aij,nj->ani", Q, points).flatten(1)


def rotation_matrix(q: torch.Tensor) -> torch.Tensor:
    """R(q) (B, 3, 3) of unit quaternions q (B, 4), body to world."""
    return (quat_outer(q) @ const("R", q)).unflatten(-1, (3, 3))


def quat_mul_pure_right(q: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """q ⊗ (0, w) for q (B, 4), w (B, 3)."""
    return (q.unsqueeze(-1) * w.unsqueeze(-2)).flatten(-2) @ const("q_x_pure", q)


def quat_mul_pure_left(w: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """(0, w) ⊗ q for w (B, 3), q (B, 4)."""
    return (w.unsqueeze(-1) * q.unsqueeze(-2)).flatten(-2) @ const("pure_x_q", q)


def normalize_quat(q: torch.Tensor) -> torch.Tensor:
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)


def skew(r: torch.Tensor) -> torch.Tensor:
    """[r]× (..., 3, 3) of r (..., 3), so that [r]× u = r × u."""
    return (r @ const("skew", r)).unflatten(-1, (3, 3))


def soft_clamp(x: torch.Tensor, low: float, high: float, width: float) -> torch.Tensor:
    """x − w·sp((x − high)/w) + w·sp((low − x)/w), sp = softplus (docs/models.md §2.2).

    Equal to x to machine precision more than ~40·w away from the limits, tends to the limits far
    outside them, C∞ everywhere (a hard clamp has zero gradient where it binds).
    """
    sp = functools.partial(F.softplus, beta=1.0 / width, threshold=40.0)
    return x - sp(x - high) + sp(low - x)


def check_unit_quaternion_state(s0: torch.Tensor) -> None:
    """RispError unless s0[:, 3:7] (qw, qx, qy, qz) are unit quaternions (|‖q‖ − 1| ≤ 1e-2)."""
    norm = torch.linalg.vector_norm(s0[:, 3:7], dim=-1)
    if bool(((norm - 1).abs() > 1e-2).any()):
        raise RispError(f"s0[:, 3:7] (qw, qx, qy, qz) must be unit quaternions, got norm {norm.min().item():.4g}")


def rigid_to_env_state(states: torch.Tensor) -> torch.Tensor:
    """(..., ≥7) states starting with position (3) and quaternion (4) -> (..., 6) = (x, y, z, yaw, pitch, roll)."""
    q = normalize_quat(states[..., 3:7])
    return torch.cat([states[..., :3], quat_to_euler(q)], -1)
