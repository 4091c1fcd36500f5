"""A vehicle mesh from a file (issue 10, item 5: `--mesh`): OBJ/PLY/STL read into body-frame parts, posed by the
state, drawn by the renderer in place of the built-in quadrotor (make-video and the tasks), and one clear line for
a missing, corrupt, empty, non-metre or misplaced mesh."""

import json
import os

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from tasks_helpers import RES, box_mesh, shared_model, shared_video, vehicle_obj

pytest.importorskip("av")
pytestmark = pytest.mark.timeout(600)


def test_read_vehicle_mesh_keeps_named_parts_and_materials(tmp_path):
    import trimesh

    from risp_data.envs.quadrotor import make_environment, read_vehicle_mesh

    parts = read_vehicle_mesh(vehicle_obj(tmp_path))
    assert set(parts) == {"frame", "rotor_front"}
    assert parts["frame"][0].shape == (8, 3) and parts["frame"][1].shape == (12, 3)
    assert np.allclose(parts["rotor_front"][0].mean(0), [0.3, 0, 0.05])
    # a single-body PLY / STL becomes the part 'frame' (object colour)
    box = trimesh.Trimesh(*box_mesh((0, 0, 0), (0.2, 0.2, 0.05)), process=False)
    for ext in ("ply", "stl"):
        box.export(tmp_path / f"box.{ext}")
        (v, f), = read_vehicle_mesh(str(tmp_path / f"box.{ext}")).values()
        assert len(f) == 12 and np.allclose(np.abs(v).max(0), [0.2, 0.2, 0.05], atol=1e-6)
    # posed: v_world = R(yaw, pitch, roll) v_body + p, materials by part name
    env = make_environment(vehicle_obj(tmp_path))
    state = torch.tensor([0.1, -0.05, 1.2, np.pi / 2, 0.0, 0.0], dtype=torch.float64)
    meshes = {m.name: m for m in env.meshes(state)}
    assert meshes["frame"].material == "object" and meshes["rotor_front"].material == "rotor_front"
    centre = meshes["rotor_front"].vertices.mean(0).numpy()
    assert np.allclose(centre, [0.1, -0.05 + 0.3, 1.2 + 0.05], atol=1e-9)  # yaw 90°: body +x -> world +y


def test_text_meshes_that_are_not_utf8_are_read(tmp_path):
    """An OBJ with a Latin-1 comment (common from European CAD exports): trimesh guesses the encoding with
    charset-normalizer, a declared dependency (without it: ModuleNotFoundError inside trimesh)."""
    from risp_data.envs.quadrotor import read_vehicle_mesh

    body = "".join(f"v {x} {y} {z}\n" for x, y, z in [(0.2, 0, 0), (0, 0.2, 0), (-0.2, 0, 0.05)]) + "f 1 2 3\n"
    path = tmp_path / "latin1.obj"
    path.write_bytes("# Modèle de drone, échelle en mètres\n".encode("latin-1") + body.encode())
    (v, f), = read_vehicle_mesh(str(path)).values()
    assert v.shape == (3, 3) and f.tolist() == [[0, 1, 2]]
    assert np.allclose(v[2], [-0.2, 0, 0.05])


def test_renderer_draws_the_mesh_from_the_file(tmp_path):
    """Same state, look and seed: the built-in vehicle and a 0.5 m plain box give different images, and a box
    twice as large covers more pixels (the file's geometry is what is drawn)."""
    from risp_data.envs.quadrotor import make_environment
    from risp_data.psi import nominal_rendering
    from risp_data.render import Renderer

    state = np.array([0.0, 0.0, 1.15, 0.3, 0.0, 0.0])
    look = nominal_rendering("quadrotor", "train")
    default = Renderer("quadrotor", resolution=32, spp=4)
    builtin = default.render(state, look, seed=1, jacobian=False)[0]
    small = Renderer(make_environment(vehicle_obj(tmp_path, 1.0, "s.obj")), resolution=32, spp=4)
    large = Renderer(make_environment(vehicle_obj(tmp_path, 1.6, "l.obj")), resolution=32, spp=4)
    img_s = small.render(state, look, seed=1, jacobian=False)[0]
    img_l = large.render(state, look, seed=1, jacobian=False)[0]
    assert np.abs(img_s - builtin).mean() > 0.01
    red = lambda im: ((im[..., 0] > 1.5 * im[..., 1]) & (im[..., 0] > 0.05)).sum()  # the red front rotor
    assert red(img_l) > red(img_s) > 0


@pytest.fixture(scope="module")
def quad(tmp_path_factory):
    return shared_model(tmp_path_factory, "quadrotor"), shared_video(tmp_path_factory, "quadrotor")


def test_make_video_and_imitate_with_a_mesh(quad, tmp_path):
    """make-video --mesh renders the file's vehicle (frames differ from the built-in one, same seed) and records
    the mesh's checksum; imitate --mesh renders it in the loop (pixelwise loss) and its gradient reaches the actions
    (lowering the loss in two iterations is not asserted: see test_tasks_run.py's render-loss test)."""
    from risp_tasks.cli import cli
    from risp_tasks.tasks.config import TaskConfig
    from risp_tasks.tasks.run import run_task
    from risp_tasks.video import read_video, sha256_file

    model, _ = quad
    mesh = vehicle_obj(tmp_path)
    runner = CliRunner()
    for name, extra in (("plain", []), ("mesh", ["--mesh", mesh])):
        res = runner.invoke(cli, ["make-video", "--env", "quadrotor", "--out", str(tmp_path / f"{name}.mp4"),
                                  "--frames", "4", "--resolution", str(RES), "--spp", "2", "--seed", "3", "--quiet"]
                            + extra)
        assert res.exit_code == 0, res.output
    truth = json.load(open(tmp_path / "mesh.truth.json"))
    assert truth["mesh"] == {"path": mesh, "sha256": sha256_file(mesh)}
    assert json.load(open(tmp_path / "plain.truth.json"))["mesh"] is None
    a, b = (read_video(str(tmp_path / f"{n}.mp4"), resolution=RES).frames for n in ("plain", "mesh"))
    assert np.abs(a - b).mean() > 0.005
    runs = {name: run_task(TaskConfig(task="imitate", video=str(tmp_path / "mesh.mp4"), out=str(tmp_path / name),
                                      model=model, mesh=m, loss="pixelwise", iterations=2, spp=2, progress=False,
                                      plots=m is not None), echo=lambda s: None)
            for name, m in (("imit", mesh), ("builtin", None))}
    result = runs["imit"]
    assert result["config"]["mesh"] == mesh
    assert abs(result["loss"][0] - runs["builtin"]["loss"][0]) > 1e-4  # the loop draws the file's vehicle
    # its gradient reaches the actions: with deterministic renders the loss moves only if the first step moved
    # them (the estimates are the best iterate, which may be the initial actions)
    loss = result["loss"]
    assert np.isfinite(loss).all() and abs(loss[1] - loss[0]) > 1e-9 * abs(loss[0]), loss
    assert os.path.isfile(tmp_path / "imit" / "frames.png")


def _invoke(args, tmp_path):
    from risp_tasks.cli import cli

    res = CliRunner().invoke(cli, args + ["--quiet"])
    lines = [ln for ln in res.output.splitlines() if ln.strip() and not ln.startswith("model: ")]
    assert res.exit_code != 0, res.output
    assert len(lines) == 1 and lines[0].startswith("Error: "), res.output
    return lines[0]


def test_bad_meshes_are_one_line_errors(quad, tmp_path):
    model, video = quad
    (tmp_path / "junk.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n" + os.urandom(64))
    (tmp_path / "notes.obj").write_text("these are notes, not a mesh\n")
    (tmp_path / "vehicle.fbx").write_text("x")
    cases = {"missing.obj": "mesh file not found", "junk.ply": "junk.ply", "notes.obj": "no triangles",
             "vehicle.fbx": "unsupported mesh format", "mm.obj": "expected metres"}
    vehicle_obj(tmp_path, 1000.0, "mm.obj")  # millimetres
    for name, words in cases.items():
        out = tmp_path / f"res-{name}"
        line = _invoke(["imitate", video, "--model", model, "--mesh", str(tmp_path / name), "--out", str(out),
                        "--iterations", "1", "--no-plots"], tmp_path)
        assert name in line and words in line, line
        assert not out.exists()
        video_out = tmp_path / f"v-{name}.mp4"
        line = _invoke(["make-video", "--env", "quadrotor", "--out", str(video_out), "--frames", "2",
                        "--resolution", "8", "--mesh", str(tmp_path / name)], tmp_path)
        assert name in line and words in line, line
        assert not video_out.exists()
    line = _invoke(["make-video", "--env", "cube", "--out", str(tmp_path / "c.mp4"), "--frames", "2",
                    "--mesh", vehicle_obj(tmp_path)], tmp_path)
    assert "vehicle.obj" in line and "the cube takes none" in line
