"""Cube: a rigid cube over a floor (z = 0).

State (6): x, y, z [m] of the centre, yaw, pitch, roll [rad] (R = Rz(yaw) Ry(pitch) Rx(roll)).
Target (9): x, y, z and the first two columns of R (r00, r10, r20, r01, r11, r21): the orientation is
uniform on SO(3), where Euler sin/cos targets are discontinuous (meshes.rot6d_state_to_target).
Geometry constants are shared with the simulator (risp_tasks.sims.cube).

Appearance: a colour cube.  The body takes the object colour ψ; each face carries one square sticker
(a thin box of side 2·STICKER_HALF standing STICKER_RAISE proud of the face) in its own fixed colour
(risp_data/envs/materials.py), numbered like a die: +x 1, +y 2, +z 3, −z 4, −y 5, −x 6.  Six distinct
colours remove the cube's 24-fold rotational symmetry: the identity is the only rotation that maps every
sticker onto a sticker of its colour, and any two visible faces fix the rotation.  (The die pips used
before were 2–3 pixels at 64×64 and the cube's attitude stayed unlearned: docs/RESULTS.md.)
"""

CUBE_SIDE = 0.2  # m (edge length)
CUBE_MASS = 1.0  # kg (simulator default)
STICKER_HALF = 0.07  # m, half side of a face's square sticker (14 of the face's 20 cm: ~8 pixels at 64×64)
STICKER_RAISE = 0.001  # m, stickers stand this far proud of the face (and reach 2 mm into the cube)
STICKER_DEPTH = 0.002  # m, how far a sticker reaches into the cube (no gap where it meets the face)

# --- Rendering (risp_data): mesh, camera, sampler -----------------------------------------------------

import math  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from .base import Camera, Environment, Mesh  # noqa: E402
from .meshes import (  # noqa: E402
    RIGID_STATE_NAMES,
    ROT6D_TARGET_NAMES,
    box,
    rigid_pose,
    rot6d_state_to_target,
    rot6d_target_to_state,
    transform,
)
from .rotations import quat_to_euler  # noqa: E402

# Framing (issue 8): the 0.2 m cube spans 14-26 of 64 pixels (median 18; a sticker ~8) over this range
# seen from 45° above at 1.4 m (fov 43°); earlier x, y ∈ ±0.5 m, z ≤ 1 m gave 7-16 pixels.  The camera is close
# because depth along its ray shows only through apparent size s (δd ≈ d·δs/s): at 2 m (fov 30°, the same
# framing) the network's position error was 97 % depth, 0.38× `average`; at 1.4 m 0.30× (docs/RESULTS.md).
XY_RANGE = 0.25  # x, y ∈ [−0.25, 0.25] m
Z_MAX = 0.6  # m, highest sampled centre height
# Documented sampler box; z's lower bound is the resting height of an axis-aligned cube (the sampler's
# actual lower bound depends on the orientation: the lowest vertex touches the floor).
STATE_LOW = (-XY_RANGE, -XY_RANGE, CUBE_SIDE / 2, -math.pi, -math.pi / 2, -math.pi)
STATE_HIGH = (XY_RANGE, XY_RANGE, Z_MAX, math.pi, math.pi / 2, math.pi)
CAMERA = Camera(origin=(0.0, -0.99, 1.34), target=(0.0, 0.0, 0.35), up=(0.0, 0.0, 1.0), fov=43.0)


# face value -> (axis, sign) of the face normal (numbered like a die: opposite faces sum to 7, and 1, 2, 3 run
# counter-clockwise around their common corner)
FACE_NORMALS = {1: (0, 1), 2: (1, 1), 3: (2, 1), 4: (2, -1), 5: (1, -1), 6: (0, -1)}


def sticker_meshes() -> dict[int, tuple[torch.Tensor, torch.Tensor]]:
    """Body-frame stickers {face value: (vertices, faces)}: a square box of half side STICKER_HALF centred on
    the face with normal sign·e_axis, spanning depth [h − STICKER_DEPTH, h + STICKER_RAISE] along the normal
    (h = CUBE_SIDE/2)."""
    h = CUBE_SIDE / 2
    out = {}
    for value, (axis, sign) in FACE_NORMALS.items():
        half, centre = [STICKER_HALF] * 3, [0.0] * 3
        half[axis] = (STICKER_DEPTH + STICKER_RAISE) / 2
        centre[axis] = sign * (h + (STICKER_RAISE - STICKER_DEPTH) / 2)
        out[value] = box(half, centre)
    return out


def meshes(states: torch.Tensor) -> list[Mesh]:
    """The cube (side CUBE_SIDE, material "object") and its stickers (materials "sticker1" … "sticker6")
    posed by states (..., 6): v_world = R(yaw, pitch, roll) v_body + p."""
    v, f = box((CUBE_SIDE / 2,) * 3)
    R, t = rigid_pose(states)
    out = [Mesh("cube", transform(v.to(states.dtype), R, t), f, "object")]
    for value, (sv, sf) in sticker_meshes().items():
        out.append(Mesh(f"sticker{value}", transform(sv.to(states.dtype), R, t), sf, f"sticker{value}"))
    return out


def sample_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 6) states: x, y uniform in [−XY_RANGE, XY_RANGE]; orientation uniform on SO(3) (normalised Gaussian
    quaternion, converted to yaw/pitch/roll); z uniform between resting on the floor (lowest vertex at
    z = 0, i.e. z = CUBE_SIDE/2 · Σ_j |R_2j|, raised by STICKER_RAISE so that no sticker dips into the floor)
    and Z_MAX."""
    n = int(n)
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    euler = quat_to_euler(torch.from_numpy(q)).numpy()  # (yaw, pitch, roll)
    R = rigid_pose(torch.from_numpy(np.c_[np.zeros((n, 3)), euler]))[0].numpy()
    z_rest = CUBE_SIDE / 2 * np.abs(R[:, 2, :]).sum(-1) + STICKER_RAISE
    xy = rng.uniform(-XY_RANGE, XY_RANGE, size=(n, 2))
    z = z_rest + rng.uniform(0.0, 1.0, size=n) * (Z_MAX - z_rest)
    return np.c_[xy, z, euler]


def make_environment() -> Environment:
    return Environment(
        name="cube",
        state_names=RIGID_STATE_NAMES,
        target_names=ROT6D_TARGET_NAMES,
        state_low=STATE_LOW,
        state_high=STATE_HIGH,
        camera=CAMERA,
        state_to_target=rot6d_state_to_target,
        target_to_state=rot6d_target_to_state,
        meshes=meshes,
        sample_states=sample_states,
        floor_height=0.0,
        description="rigid cube with one coloured sticker per face, over a floor",
    )
