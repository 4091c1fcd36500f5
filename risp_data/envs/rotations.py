"""Rotation conventions shared by rendering, simulation and tasks (torch, differentiable).

Euler angles are (yaw, pitch, roll) with the body-to-world rotation

    R(yaw, pitch, roll) = Rz(yaw) · Ry(pitch) · Rx(roll)          (intrinsic Z-Y'-X'')

and quaternions are scalar-first (w, x, y, z), body to world.  World frame: z up.
"""

from __future__ import annotations

import torch


def euler_to_matrix(yaw: torch.Tensor, pitch: torch.Tensor, roll: torch.Tensor) -> torch.Tensor:
    """R = Rz(yaw) Ry(pitch) Rx(roll); inputs of shape (...), output (..., 3, 3)."""
    cy, sy = torch.cos(yaw), torch.sin(yaw)
    cp, sp = torch.cos(pitch), torch.sin(pitch)
    cr, sr = torch.cos(roll), torch.sin(roll)
    row0 = torch.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1)
    row1 = torch.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1)
    row2 = torch.stack([-sp, cp * sr, cp * cr], -1)
    return torch.stack([row0, row1, row2], -2)


def matrix_to_euler(R: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`euler_to_matrix` (pitch in [-pi/2, pi/2]); returns (..., 3) = (yaw, pitch, roll).

    At gimbal lock (|R₂₀| = 1: pitch ±π/2, a cube resting on a side face) the angles are not differentiable;
    the gradient there is made finite instead of NaN: the asin argument is clamped to ±(1 − ε) (ε the dtype's
    machine epsilon; the value moves by at most √(2ε): 2e-8 rad in float64), and atan2(0, 0) gets a zero
    gradient (:func:`_atan2`).  Without this one resting cube made a whole task's gradient NaN."""
    one = 1.0 - torch.finfo(R.dtype).eps if R.is_floating_point() else 1.0
    yaw = _atan2(R[..., 1, 0], R[..., 0, 0])
    pitch = torch.asin(torch.clamp(-R[..., 2, 0], -one, one))
    roll = _atan2(R[..., 2, 1], R[..., 2, 2])
    return torch.stack([yaw, pitch, roll], -1)


def _atan2(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """atan2(y, x), with a zero instead of a NaN gradient at y = x = 0 (where atan2's gradient (x, −y)/(x² + y²)
    is 0/0): such entries are evaluated at (0, 1), i.e. the angle 0 (torch.atan2(+0, +0) is 0 as well)."""
    zero = (x == 0) & (y == 0)
    return torch.atan2(torch.where(zero, torch.zeros_like(y), y), torch.where(zero, torch.ones_like(x), x))


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Scalar-first unit quaternion (..., 4) -> rotation matrix (..., 3, 3)."""
    w, x, y, z = q.unbind(-1)
    row0 = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1)
    row1 = torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1)
    row2 = torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)
    return torch.stack([row0, row1, row2], -2)


def euler_to_quat(yaw: torch.Tensor, pitch: torch.Tensor, roll: torch.Tensor) -> torch.Tensor:
    """Quaternion (w, x, y, z) of Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy = torch.cos(yaw / 2), torch.sin(yaw / 2)
    cp, sp = torch.cos(pitch / 2), torch.sin(pitch / 2)
    cr, sr = torch.cos(roll / 2), torch.sin(roll / 2)
    return torch.stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ],
        -1,
    )


def quat_to_euler(q: torch.Tensor) -> torch.Tensor:
    """Scalar-first quaternion (..., 4) -> (..., 3) = (yaw, pitch, roll)."""
    return matrix_to_euler(quat_to_matrix(q))
