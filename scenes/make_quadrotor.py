"""Generate the quadrotor meshes in this folder (deterministic; run ``python scenes/make_quadrotor.py``).

Writes the ASCII PLY files ``quadrotor_frame.ply``, ``quadrotor_rotor_front.ply`` (red front rotor),
``quadrotor_rotor_left.ply`` (white left rotor) and ``quadrotor_rotors.ply`` (back and right rotors) from the trimesh
construction in ``risp_data/envs/quadrotor_mesh.py`` (which documents the parts and the body frame);
an installed package without this folder builds the same meshes in memory from that module.
"""

from __future__ import annotations

import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from risp_data.envs.quadrotor import MESH_FILES  # noqa: E402
from risp_data.envs.quadrotor_mesh import ROTOR_PARTS, frame_mesh, rotor_mesh  # noqa: E402


def write_ply(mesh, path: str) -> None:
    """ASCII PLY with vertices and faces only, written to a temporary name and renamed."""
    import trimesh

    data = trimesh.exchange.ply.export_ply(mesh, encoding="ascii", vertex_normal=False, include_attributes=False)
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def main(out_dir: str = HERE) -> None:
    write_ply(frame_mesh(), os.path.join(out_dir, MESH_FILES["frame"]))
    for part, indices in ROTOR_PARTS.items():
        write_ply(rotor_mesh(indices), os.path.join(out_dir, MESH_FILES[part]))


if __name__ == "__main__":
    main()
