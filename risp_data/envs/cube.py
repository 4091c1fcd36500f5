"""Cube: a rigid cube over a floor (z = 0).

State (6): x, y, z [m] of the centre, yaw, pitch, roll [rad] (R = Rz(yaw) Ry(pitch) Rx(roll)).
Target (9): x, y, z, sin yaw, sin pitch, sin roll, cos yaw, cos pitch, cos roll.
Geometry constants are shared with the simulator (risp_tasks.sims.cube).
"""

CUBE_SIDE = 0.2  # m (edge length)
CUBE_MASS = 1.0  # kg (simulator default)

# --- Rendering (risp_data): mesh, camera, sampler -----------------------------------------------------

import math  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from .base import Camera, Environment, Mesh  # noqa: E402
from .meshes import (  # noqa: E402
    RIGID_STATE_NAMES,
    RIGID_TARGET_NAMES,
    box,
    rigid_pose,
    rigid_state_to_target,
    rigid_target_to_state,
    transform,
)
from .rotations import quat_to_euler  # noqa: E402

XY_RANGE = 0.5  # x, y ∈ [−0.5, 0.5] m
Z_MAX = 1.0  # m, highest sampled centre height
# Documented sampler box; z's lower bound is the resting height of an axis-aligned cube (the sampler's
# actual lower bound depends on the orientation: the lowest vertex touches the floor).
STATE_LOW = (-XY_RANGE, -XY_RANGE, CUBE_SIDE / 2, -math.pi, -math.pi / 2, -math.pi)
STATE_HIGH = (XY_RANGE, XY_RANGE, Z_MAX, math.pi, math.pi / 2, math.pi)
CAMERA = Camera(origin=(0.0, -2.3, 1.5), target=(0.0, 0.0, 0.45), up=(0.0, 0.0, 1.0), fov=40.0)


def meshes(states: torch.Tensor) -> list[Mesh]:
    """The cube (side CUBE_SIDE) posed by states (..., 6): v_world = R(yaw, pitch, roll) v_body + p."""
    v, f = box((CUBE_SIDE / 2,) * 3)
    R, t = rigid_pose(states)
    return [Mesh("cube", transform(v.to(states.dtype), R, t), f, "object")]


def sample_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 6) states: x, y uniform in [−0.5, 0.5]; orientation uniform on SO(3) (normalised Gaussian
    quaternion, converted to yaw/pitch/roll); z uniform between resting on the floor (lowest vertex at
    z = 0, i.e. z = CUBE_SIDE/2 · Σ_j |R_2j|) and Z_MAX."""
    n = int(n)
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    euler = quat_to_euler(torch.from_numpy(q)).numpy()  # (yaw, pitch, roll)
    R = rigid_pose(torch.from_numpy(np.c_[np.zeros((n, 3)), euler]))[0].numpy()
    z_rest = CUBE_SIDE / 2 * np.abs(R[:, 2, :]).sum(-1)
    xy = rng.uniform(-XY_RANGE, XY_RANGE, size=(n, 2))
    z = z_rest + rng.uniform(0.0, 1.0, size=n) * (Z_MAX - z_rest)
    return np.c_[xy, z, euler]


def make_environment() -> Environment:
    return Environment(
        name="cube",
        state_names=RIGID_STATE_NAMES,
        target_names=RIGID_TARGET_NAMES,
        state_low=STATE_LOW,
        state_high=STATE_HIGH,
        camera=CAMERA,
        state_to_target=rigid_state_to_target,
        target_to_state=rigid_target_to_state,
        meshes=meshes,
        sample_states=sample_states,
        floor_height=0.0,
        description="rigid cube over a floor",
    )
