"""The quadrotor's body-frame meshes, built deterministically from trimesh primitives.

Body frame (see quadrotor.py): x forward, z the thrust axis, origin at the body centre.  Parts, sized
by the constants shared with the simulator:

- frame : central body box, four arms (boxes) in a "+" layout, four motor pods (cylinders) and a small
  camera pod at the front — rendered with the object reflectance ψ;
- rotor_front, rotor_left, rotors: thin rotor discs of radius ROTOR_RADIUS at height ROTOR_HEIGHT above
  the body centre, each with two crossed blades.  As on real vehicles the rotors are coloured so that
  the image shows front/back and left/right (a plain "+" quadrotor is 4-fold symmetric: yaw would be
  ambiguous modulo 90°): the front rotor (0, +x) is red, the left rotor (1, +y) white, the back and
  right rotors (2, 3) dark grey (materials in risp_data/envs/materials.py).

Rotor i sits at ARM_LENGTH · (cos(i·π/2), sin(i·π/2), 0), i = 0..3 (0: +x, 1: +y, 2: −x, 3: −y).
``scenes/make_quadrotor.py`` writes these meshes to the PLY files in ``scenes/`` (the source of truth
of a source checkout); ``quadrotor.body_meshes`` falls back to building them here when that folder is
not there (an installed, non-editable package).
"""

from __future__ import annotations

import math

import numpy as np

from .quadrotor import ARM_LENGTH, BODY_HALF_EXTENTS, ROTOR_HEIGHT, ROTOR_RADIUS

ARM_WIDTH = 0.03  # m
POD_RADIUS = 0.03  # m, motor pod under each rotor
SECTIONS = 24


def _translated(mesh, offset):
    mesh.apply_translation(np.asarray(offset, np.float64))
    return mesh


def frame_mesh():
    """Body, arms, motor pods and a camera pod, as one ``trimesh.Trimesh``."""
    import trimesh

    hx, hy, hz = BODY_HALF_EXTENTS
    parts = [trimesh.creation.box(extents=(2 * hx, 2 * hy, 2 * hz))]
    parts.append(_translated(trimesh.creation.box(extents=(0.04, 0.05, 0.04)), (hx + 0.02, 0.0, -0.01)))
    for i in range(4):
        c, s = math.cos(i * math.pi / 2), math.sin(i * math.pi / 2)
        arm = trimesh.creation.box(extents=(ARM_LENGTH, ARM_WIDTH, ARM_WIDTH))
        angle = trimesh.transformations.rotation_matrix(i * math.pi / 2, (0, 0, 1))
        arm.apply_transform(angle)
        parts.append(_translated(arm, (c * ARM_LENGTH / 2, s * ARM_LENGTH / 2, 0.0)))
        pod_height = ROTOR_HEIGHT + ARM_WIDTH
        pod = trimesh.creation.cylinder(radius=POD_RADIUS, height=pod_height, sections=SECTIONS)
        parts.append(_translated(pod, (c * ARM_LENGTH, s * ARM_LENGTH, ROTOR_HEIGHT / 2 - ARM_WIDTH / 2)))
    return trimesh.util.concatenate(parts)


ROTOR_PARTS = {"rotor_front": (0,), "rotor_left": (1,), "rotors": (2, 3)}  # part -> rotor indices


def rotor_mesh(indices=(0, 1, 2, 3)):
    """Rotor discs ``indices`` with two crossed blades each, as one ``trimesh.Trimesh``."""
    import trimesh

    parts = []
    for i in indices:
        c, s = math.cos(i * math.pi / 2), math.sin(i * math.pi / 2)
        centre = (c * ARM_LENGTH, s * ARM_LENGTH, ROTOR_HEIGHT)
        disc = trimesh.creation.cylinder(radius=ROTOR_RADIUS, height=0.006, sections=SECTIONS * 2)
        parts.append(_translated(disc, centre))
        for angle in (math.pi / 4 + i * 0.3, 3 * math.pi / 4 + i * 0.3):
            blade = trimesh.creation.box(extents=(2 * ROTOR_RADIUS * 0.95, 0.025, 0.012))
            blade.apply_transform(trimesh.transformations.rotation_matrix(angle, (0, 0, 1)))
            parts.append(_translated(blade, (centre[0], centre[1], ROTOR_HEIGHT + 0.006)))
    return trimesh.util.concatenate(parts)


def build_meshes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{part: (vertices (V, 3) float64, faces (F, 3) int64)} for the parts "frame" and ROTOR_PARTS."""
    out = {}
    parts = [("frame", frame_mesh())] + [(part, rotor_mesh(idx)) for part, idx in ROTOR_PARTS.items()]
    for part, mesh in parts:
        out[part] = (np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64))
    return out
