"""Generate the quadrotor meshes in this folder (deterministic; run ``python scenes/make_quadrotor.py``).

Body frame (see risp_data/envs/quadrotor.py): x forward, z the thrust axis, origin at the body centre.
Writes two ASCII PLY files made of trimesh primitives, sized by the constants shared with the simulator:

- ``quadrotor_frame.ply``  : central body box, four arms (boxes) in a "+" layout, four motor pods
  (cylinders) and a small camera pod at the front — rendered with the object reflectance ψ;
- ``quadrotor_rotors.ply`` : four thin rotor discs of radius ROTOR_RADIUS at height ROTOR_HEIGHT above
  the body centre, each with two crossed blades — rendered dark grey.

Rotor i sits at ARM_LENGTH · (cos(i·π/2), sin(i·π/2), 0), i = 0..3 (0: +x, 1: +y, 2: −x, 3: −y).
"""

from __future__ import annotations

import math
import os
import sys

import numpy as np
import trimesh

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from risp_data.envs.quadrotor import ARM_LENGTH, BODY_HALF_EXTENTS, ROTOR_HEIGHT, ROTOR_RADIUS  # noqa: E402

ARM_WIDTH = 0.03  # m
POD_RADIUS = 0.03  # m, motor pod under each rotor
SECTIONS = 24


def _translated(mesh: trimesh.Trimesh, offset) -> trimesh.Trimesh:
    mesh.apply_translation(np.asarray(offset, np.float64))
    return mesh


def frame_mesh() -> trimesh.Trimesh:
    """Body, arms, motor pods and a camera pod, as one mesh."""
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


def rotor_mesh() -> trimesh.Trimesh:
    """Four rotor discs with two crossed blades each, as one mesh."""
    parts = []
    for i in range(4):
        c, s = math.cos(i * math.pi / 2), math.sin(i * math.pi / 2)
        centre = (c * ARM_LENGTH, s * ARM_LENGTH, ROTOR_HEIGHT)
        disc = trimesh.creation.cylinder(radius=ROTOR_RADIUS, height=0.006, sections=SECTIONS * 2)
        parts.append(_translated(disc, centre))
        for angle in (math.pi / 4 + i * 0.3, 3 * math.pi / 4 + i * 0.3):
            blade = trimesh.creation.box(extents=(2 * ROTOR_RADIUS * 0.95, 0.025, 0.012))
            blade.apply_transform(trimesh.transformations.rotation_matrix(angle, (0, 0, 1)))
            parts.append(_translated(blade, (centre[0], centre[1], ROTOR_HEIGHT + 0.006)))
    return trimesh.util.concatenate(parts)


def write_ply(mesh: trimesh.Trimesh, path: str) -> None:
    """ASCII PLY with vertices and faces only, written to a temporary name and renamed."""
    data = trimesh.exchange.ply.export_ply(mesh, encoding="ascii", vertex_normal=False, include_attributes=False)
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def main(out_dir: str = HERE) -> None:
    write_ply(frame_mesh(), os.path.join(out_dir, "quadrotor_frame.ply"))
    write_ply(rotor_mesh(), os.path.join(out_dir, "quadrotor_rotors.ply"))


if __name__ == "__main__":
    main()
