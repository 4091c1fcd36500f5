"""Generate the quadrotor meshes in this folder (deterministic; run ``python scenes/make_quadrotor.py``).

Writes two ASCII PLY files, ``quadrotor_frame.ply`` and ``quadrotor_rotors.ply``, from the trimesh
construction in ``risp_data/envs/quadrotor_mesh.py`` (which documents the parts and the body frame);
an installed package without this folder builds the same meshes in memory from that module.
"""

from __future__ import annotations

import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from risp_data.envs.quadrotor_mesh import frame_mesh, rotor_mesh  # noqa: E402


def write_ply(mesh, path: str) -> None:
    """ASCII PLY with vertices and faces only, written to a temporary name and renamed."""
    import trimesh

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
