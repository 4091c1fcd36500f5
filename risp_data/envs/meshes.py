"""Small torch mesh helpers shared by the environments: boxes, cylinders, swept tubes, rigid transforms
and the pinhole projection of the environments' cameras.

All builders return ``(vertices (V, 3) float64 tensor, faces (F, 3) int64 tensor)`` in a local frame;
posing is a differentiable rigid transform ``v ↦ R v + t`` (batched over leading dimensions), so a
world-space mesh is differentiable w.r.t. whatever produced ``R`` and ``t``.  Faces are wound
counter-clockwise seen from outside (outward normals), which Mitsuba uses for flat shading.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .base import Camera
from .rotations import euler_to_matrix

# The 8 corners of the unit cube [-1, 1]^3 (index = 4·[z>0] + 2·[y>0] + [x>0]) and its 12 triangles.
_BOX_CORNERS = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], dtype=np.float64)
_BOX_FACES = np.array(
    [
        [0, 2, 3], [0, 3, 1],  # z = -1 (normal -z)
        [4, 5, 7], [4, 7, 6],  # z = +1
        [0, 1, 5], [0, 5, 4],  # y = -1
        [2, 6, 7], [2, 7, 3],  # y = +1
        [0, 4, 6], [0, 6, 2],  # x = -1
        [1, 3, 7], [1, 7, 5],  # x = +1
    ],
    dtype=np.int64,
)


def identity(x: torch.Tensor) -> torch.Tensor:
    """State <-> target map of environments whose target is the state itself (hand, rod); a copy."""
    return x.clone()


def box(half_extents, center=(0.0, 0.0, 0.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """Axis-aligned box with the given half extents around ``center`` (8 vertices, 12 triangles)."""
    v = _BOX_CORNERS * np.asarray(half_extents, dtype=np.float64) + np.asarray(center, dtype=np.float64)
    return torch.from_numpy(v), torch.from_numpy(_BOX_FACES.copy())


def box_between(low, high) -> tuple[torch.Tensor, torch.Tensor]:
    """Axis-aligned box spanning ``low``..``high`` (per-axis)."""
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    return box((high - low) / 2, (high + low) / 2)


def tube_faces(n_rings: int, n_around: int, caps: bool = True) -> torch.Tensor:
    """Triangles joining ``n_rings`` consecutive rings of ``n_around`` vertices (vertex r·n_around + k).

    Ring vertices must run counter-clockwise about the sweep direction (right-handed) for outward
    normals.  With ``caps`` the first and
    last rings are closed by fans (no extra vertices; rings are convex).
    """
    faces = []
    for r in range(n_rings - 1):
        for k in range(n_around):
            a, b = r * n_around + k, r * n_around + (k + 1) % n_around
            c, d = a + n_around, b + n_around
            faces += [[a, b, d], [a, d, c]]
    if caps:
        last = (n_rings - 1) * n_around
        for k in range(1, n_around - 1):
            faces.append([0, k + 1, k])  # first ring: normal against the sweep direction
            faces.append([last, last + k, last + k + 1])
    return torch.tensor(faces, dtype=torch.int64)


def cylinder(radius: float, z0: float, z1: float, segments: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed cylinder about the local z axis from ``z0`` to ``z1``."""
    ang = np.arange(segments) * 2 * math.pi / segments
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], -1)
    v = np.concatenate([np.c_[ring, np.full(segments, z0)], np.c_[ring, np.full(segments, z1)]])
    return torch.from_numpy(v), tube_faces(2, segments)


def transform(vertices: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Rigid transform ``R v + t``: vertices (V, 3), R (..., 3, 3), t (..., 3) -> (..., V, 3).

    Written as a broadcast product and sum rather than a matmul: these products are tiny, and MKL's
    threaded matmul took 25–100 ms for them on a loaded 2-core machine (the product takes 0.1 ms).
    """
    return (R[..., None, :, :] * vertices.to(R.dtype)[:, None, :]).sum(-1) + t[..., None, :]


def mat3_mul(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Batched 3×3 product A @ B without BLAS (see :func:`transform`)."""
    return (A[..., :, :, None] * B[..., None, :, :]).sum(-2)


def merge(parts: list[tuple[torch.Tensor, torch.Tensor]]) -> tuple[torch.Tensor, torch.Tensor]:
    """Concatenate meshes (vertices (..., V_i, 3)) into one, offsetting face indices."""
    verts, faces, offset = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + offset)
        offset += v.shape[-2]
    return torch.cat(verts, -2), torch.cat(faces, 0)


def camera_basis(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mitsuba's ``look_at`` frame: (left, up, forward) unit vectors of the camera."""
    o, t, up = (np.asarray(a, np.float64) for a in (camera.origin, camera.target, camera.up))
    fwd = (t - o) / np.linalg.norm(t - o)
    left = np.cross(up, fwd)
    left /= np.linalg.norm(left)
    return left, np.cross(fwd, left), fwd


def project(camera: Camera, points) -> np.ndarray:
    """Pinhole projection of world points (..., 3) to image coordinates (..., 2) in [0, 1]² when visible.

    Coordinates are (u, v) = (column, row) over a square image with the horizontal field of view
    ``camera.fov`` (Mitsuba ``perspective`` with ``fov_axis='x'``): u grows to the right, v downwards.
    Points behind the camera get NaN.
    """
    p = np.asarray(points, np.float64) - np.asarray(camera.origin, np.float64)
    left, up, fwd = camera_basis(camera)
    depth = p @ fwd
    scale = 1.0 / math.tan(math.radians(camera.fov) / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = 0.5 - 0.5 * scale * (p @ left) / depth
        v = 0.5 - 0.5 * scale * (p @ up) / depth
    uv = np.stack([u, v], -1)
    uv[depth <= 0] = np.nan
    return uv


# ----------------------------------------------------------------------------------------------------
# Rigid bodies (quadrotor, cube): state (x, y, z, yaw, pitch, roll) and the 9-d network target
# ----------------------------------------------------------------------------------------------------

RIGID_STATE_NAMES = ("x", "y", "z", "yaw", "pitch", "roll")
RIGID_TARGET_NAMES = ("x", "y", "z", "sin_yaw", "sin_pitch", "sin_roll", "cos_yaw", "cos_pitch", "cos_roll")


def rigid_pose(states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 6) states -> rotation (..., 3, 3) = Rz(yaw) Ry(pitch) Rx(roll) and translation (..., 3)."""
    return euler_to_matrix(states[..., 3], states[..., 4], states[..., 5]), states[..., :3]


def rigid_state_to_target(states: torch.Tensor) -> torch.Tensor:
    """(x, y, z, yaw, pitch, roll) -> (x, y, z, sin yaw, sin pitch, sin roll, cos yaw, cos pitch, cos roll)."""
    ang = states[..., 3:6]
    return torch.cat([states[..., :3], torch.sin(ang), torch.cos(ang)], -1)


def rigid_target_to_state(targets: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rigid_state_to_target`: angles = atan2(sin, cos), in (−π, π]."""
    return torch.cat([targets[..., :3], torch.atan2(targets[..., 3:6], targets[..., 6:9])], -1)


# The cube's orientation is uniform on SO(3): sin/cos of Euler angles are discontinuous there (gimbal lock
# at pitch ±π/2, roll and yaw trading places), so its network target holds the first two columns of R
# instead — the continuous "6D" representation of Zhou et al. (CVPR 2019); Gram–Schmidt maps any
# prediction back to a rotation.
ROT6D_TARGET_NAMES = ("x", "y", "z", "r00", "r10", "r20", "r01", "r11", "r21")


def rot6d_state_to_target(states: torch.Tensor) -> torch.Tensor:
    """(x, y, z, yaw, pitch, roll) -> (x, y, z, R[:, 0], R[:, 1]) with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    R = euler_to_matrix(states[..., 3], states[..., 4], states[..., 5])
    return torch.cat([states[..., :3], R[..., :, 0], R[..., :, 1]], -1)


def rot6d_target_to_state(targets: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rot6d_state_to_target` on its range; any 6-vector is projected onto a rotation
    by Gram–Schmidt (a = â/‖â‖, b = (b̂ − (a·b̂)a)/‖·‖, c = a × b), then converted to yaw, pitch, roll."""
    from .rotations import matrix_to_euler

    a = targets[..., 3:6]
    a = a / torch.linalg.vector_norm(a, dim=-1, keepdim=True).clamp_min(1e-12)
    b = targets[..., 6:9]
    b = b - (a * b).sum(-1, keepdim=True) * a
    b = b / torch.linalg.vector_norm(b, dim=-1, keepdim=True).clamp_min(1e-12)
    R = torch.stack([a, b, torch.linalg.cross(a, b)], -1)
    return torch.cat([targets[..., :3], matrix_to_euler(R)], -1)


def uniform_states(rng: np.random.Generator, n: int, low, high) -> np.ndarray:
    """(n, S) float64 states drawn uniformly and independently in the box [low, high]."""
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    return rng.uniform(low, high, size=(int(n), low.size))
