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

from ..errors import RispError, message_line  # noqa: E402
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
    if not all(os.path.exists(os.path.join(SCENES_DIR, name)) for name in MESH_FILES.values()):
        from .quadrotor_mesh import build_meshes

        return build_meshes()
    out = {}
    for part, name in MESH_FILES.items():
        path = os.path.join(SCENES_DIR, name)
        out[part] = _one_mesh(_load(path), path)
    return out


MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
MESH_EXTENT = (0.05, 5.0)  # m: the largest body-frame distance of a vehicle mesh (catches millimetre files)


def _load(path: str):
    import trimesh

    # OBJ: keep the named objects / groups apart (trimesh merges them by default)
    split = dict(split_objects=True, split_groups=True, group_material=False) if path.lower().endswith(".obj") else {}
    try:
        return trimesh.load(path, process=False, **split)
    except Exception as e:  # noqa: BLE001 - trimesh raises many kinds
        raise RispError(f"{path}: cannot read the mesh ({type(e).__name__}: {message_line(e)})") from None


def _one_mesh(mesh, path: str) -> tuple[np.ndarray, np.ndarray]:
    v, f = np.asarray(getattr(mesh, "vertices", ()), np.float64), np.asarray(getattr(mesh, "faces", ()), np.int64)
    if v.ndim != 2 or v.shape[-1] != 3 or f.ndim != 2 or f.shape[-1] != 3 or len(f) == 0:
        raise RispError(f"{path}: the mesh has no triangles (an empty, corrupt or non-mesh file)")
    if not np.all(np.isfinite(v)) or f.min() < 0 or f.max() >= len(v):
        raise RispError(f"{path}: the mesh has NaN/inf vertices or faces indexing past its {len(v)} vertices")
    return v, f


def read_vehicle_mesh(path: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """A vehicle mesh file as body-frame parts {part: (V (N, 3) float64, F (M, 3) int64)} (docs/tasks.md §Vehicle mesh).

    Body frame as above: metres, origin at the centre of mass, x forward (rotor 0), z the thrust axis.  A file
    with named objects (OBJ ``o``/``g``, glTF nodes) keeps them as parts; parts named ``rotor_front``,
    ``rotor_left`` or ``rotors`` get those fixed colours, every other part the object colour ψ.  One line of
    RispError for a missing, unreadable, empty, non-finite or implausibly sized (not metres) mesh.
    """
    import trimesh

    if not os.path.isfile(path):
        raise RispError(f"{path}: mesh file not found")
    if not path.lower().endswith(MESH_SUFFIXES):
        raise RispError(f"{path}: unsupported mesh format; use one of {', '.join(MESH_SUFFIXES)}")
    loaded = _load(path)
    parts: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if isinstance(loaded, trimesh.Scene):
        for node in loaded.graph.nodes_geometry:
            transform, geometry = loaded.graph[node]
            mesh = loaded.geometry[geometry].copy()
            mesh.apply_transform(transform)
            v, f = _one_mesh(mesh, path)
            name = str(geometry if geometry in MESH_MATERIALS else node)
            if name in parts:  # same name twice: merge (faces offset by the vertices already there)
                v0, f0 = parts[name]
                v, f = np.concatenate([v0, v]), np.concatenate([f0, f + len(v0)])
            parts[name] = (v, f)
        if not parts:
            raise RispError(f"{path}: the mesh has no triangles (an empty, corrupt or non-mesh file)")
    else:
        parts["frame"] = _one_mesh(loaded, path)
    extent = max(float(np.linalg.norm(v, axis=1).max()) for v, _ in parts.values())
    if not MESH_EXTENT[0] <= extent <= MESH_EXTENT[1]:
        raise RispError(f"{path}: the mesh reaches {extent:.3g} from its origin; expected metres in the body frame "
                        f"({MESH_EXTENT[0]}-{MESH_EXTENT[1]} m; the built-in vehicle reaches 0.42 m)")
    return parts


def posed_meshes(states: torch.Tensor, parts: dict[str, tuple[np.ndarray, np.ndarray]]) -> list[Mesh]:
    """World-space meshes of body-frame ``parts`` posed by states (..., 6): v_world = R(yaw, pitch, roll) v_body + p.
    Parts named in MESH_MATERIALS get that material, any other part the object colour ψ."""
    R, t = rigid_pose(states)
    out = []
    for part, (v, f) in parts.items():
        verts = transform(torch.as_tensor(v, dtype=states.dtype), R, t)
        out.append(Mesh(part, verts, torch.as_tensor(f), MESH_MATERIALS.get(part, "object")))
    return out


def meshes(states: torch.Tensor) -> list[Mesh]:
    """World-space meshes of the built-in quadrotor posed by states (..., 6)."""
    return posed_meshes(states, body_meshes())


def sample_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 6) states uniform in [STATE_LOW, STATE_HIGH] (free flight above the floor)."""
    return uniform_states(rng, n, STATE_LOW, STATE_HIGH)


def make_environment(mesh: str | None = None) -> Environment:
    """The quadrotor; ``mesh``: a vehicle mesh file (:func:`read_vehicle_mesh`) replacing the built-in meshes in
    rendering (the simulator's geometry — arm length, inertia — stays nominal)."""
    if mesh is None:
        mesh_fn, description = meshes, "rigid quadrotor (body, four arms, four rotors) in free flight above a floor"
    else:
        parts = read_vehicle_mesh(mesh)

        def mesh_fn(states: torch.Tensor) -> list[Mesh]:
            return posed_meshes(states, parts)

        description = f"rigid quadrotor in free flight above a floor, vehicle mesh {mesh}"
    return Environment(
        name="quadrotor",
        state_names=RIGID_STATE_NAMES,
        target_names=RIGID_TARGET_NAMES,
        state_low=STATE_LOW,
        state_high=STATE_HIGH,
        camera=CAMERA,
        state_to_target=rigid_state_to_target,
        target_to_state=rigid_target_to_state,
        meshes=mesh_fn,
        sample_states=sample_states,
        floor_height=0.0,
        description=description,
    )
