"""Quadrotor: a rigid body in free flight.

State (6): x, y, z [m], yaw, pitch, roll [rad] with R = Rz(yaw) Ry(pitch) Rx(roll) (see rotations.py).
Target (9): x, y, z, sin yaw, sin pitch, sin roll, cos yaw, cos pitch, cos roll.

Geometry constants below are shared with the simulator (risp_tasks.sims.quadrotor): rotors sit in a
"+" layout in the body frame, rotor i at ARM_LENGTH · (cos(i·π/2), sin(i·π/2), 0), i = 0..3
(0: +x, 1: +y, 2: −x, 3: −y); body x is forward, body z is the thrust axis.
"""

ARM_LENGTH = 0.3  # m, body centre to rotor axis
ROTOR_RADIUS = 0.12  # m
BODY_HALF_EXTENTS = (0.08, 0.08, 0.04)  # m
ROTOR_HEIGHT = 0.03  # m, rotor plane above the body centre

# --- Rendering (risp_data): mesh, camera, sampler -----------------------------------------------------

import math  # noqa: E402
import os  # noqa: E402
from functools import lru_cache  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from ..errors import RispError  # noqa: E402
from .base import Camera, Environment, Mesh  # noqa: E402
from .meshes import (  # noqa: E402
    RIGID_STATE_NAMES,
    RIGID_TARGET_NAMES,
    rigid_pose,
    rigid_state_to_target,
    rigid_target_to_state,
    transform,
    uniform_states,
)

SCENES_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "scenes")
MESH_FILES = {"frame": "quadrotor_frame.ply", "rotor_front": "quadrotor_rotor_front.ply",
              "rotor_left": "quadrotor_rotor_left.ply", "rotors": "quadrotor_rotors.ply"}  # scenes/make_quadrotor.py
# (from quadrotor_mesh.py; without a scenes/ folder next to the package the meshes are built in memory)
# frame: object colour ψ; front rotor red, left rotor white, back/right rotors dark (envs/materials.py)
MESH_MATERIALS = {"frame": "object", "rotor_front": "rotor_front", "rotor_left": "rotor_left", "rotors": "rotor"}

# Sampler ranges (x, y, z [m], yaw, pitch, roll [rad]); the floor is at z = 0.  Framing (issue 8): the
# 0.84 m-wide quadrotor must span >= ~30 of 64 pixels to show its attitude, so the flight volume is a
# 0.36 × 0.36 × 0.3 m box seen from 75° above the horizon at 1.9 m (fov 40°): 29-43 pixels across
# (benchmarks/object_coverage.py; docs/environments.md §Framing).  Earlier: a 0.8 m cube, 15-28 pixels.
STATE_LOW = (-0.18, -0.18, 1.0, -math.pi, -math.pi / 6, -math.pi / 6)
STATE_HIGH = (0.18, 0.18, 1.3, math.pi, math.pi / 6, math.pi / 6)
CAMERA = Camera(origin=(0.0, -0.49, 2.985), target=(0.0, 0.0, 1.15), up=(0.0, 0.0, 1.0), fov=40.0)


@lru_cache(maxsize=None)
def body_meshes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The quadrotor's body-frame meshes {part: (vertices (V, 3) float64, faces (F, 3) int64)}.

    Read from the PLY files in the repository's ``scenes/`` folder; when that folder is missing (a
    non-editable install ships no ``scenes/``) the same meshes are built in memory by
    :func:`quadrotor_mesh.build_meshes`, the construction the PLY files were written from.
    """
    import trimesh

    if not all(os.path.exists(os.path.join(SCENES_DIR, name)) for name in MESH_FILES.values()):
        from .quadrotor_mesh import build_meshes

        return build_meshes()
    out = {}
    for part, name in MESH_FILES.items():
        path = os.path.join(SCENES_DIR, name)
        try:
            mesh = trimesh.load(path, process=False, force="mesh")
        except Exception as e:  # noqa: BLE001 - trimesh raises many kinds
            raise RispError(f"cannot read quadrotor mesh {path}: {e}") from None
        out[part] = (np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64))
    return out


def meshes(states: torch.Tensor) -> list[Mesh]:
    """World-space meshes of the quadrotor posed by states (..., 6): v_world = R(yaw, pitch, roll) v_body + p."""
    R, t = rigid_pose(states)
    out = []
    for part, (v, f) in body_meshes().items():
        verts = transform(torch.as_tensor(v, dtype=states.dtype), R, t)
        out.append(Mesh(part, verts, torch.as_tensor(f), MESH_MATERIALS[part]))
    return out


def sample_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 6) states uniform in [STATE_LOW, STATE_HIGH] (free flight above the floor)."""
    return uniform_states(rng, n, STATE_LOW, STATE_HIGH)


def make_environment() -> Environment:
    return Environment(
        name="quadrotor",
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
        description="rigid quadrotor (body, four arms, four rotors) in free flight above a floor",
    )
