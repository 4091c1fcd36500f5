"""Environments (issue 2, item 2): state/target maps, differentiable meshes, samplers, cameras."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
import torch

from risp_data.envs import ENV_NAMES, Environment, get_environment
from risp_data.envs import cube, hand, quadrotor, rod
from risp_data.envs.meshes import box, cylinder, project, tube_faces
from risp_data.errors import RispError

DIMS = {"quadrotor": (6, 9), "cube": (6, 9), "hand": (13, 13), "rod": (10, 10)}


def signed_volume(vertices: torch.Tensor, faces: torch.Tensor) -> float:
    """Volume enclosed by a closed triangle mesh (positive when normals point outwards)."""
    v = vertices.detach().double()
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return float((a * torch.cross(b, c, dim=-1)).sum() / 6)


@pytest.mark.parametrize("name", ENV_NAMES)
def test_environment_shapes_and_names(name):
    env = get_environment(name)
    assert isinstance(env, Environment) and env.name == name
    assert (env.state_dim, env.target_dim) == DIMS[name]
    assert len(env.state_low) == len(env.state_high) == env.state_dim
    assert all(lo < hi for lo, hi in zip(env.state_low, env.state_high))
    names = env.state_names + env.target_names
    assert all(n.replace("_", "").isalnum() and n == n.lower() and "." not in n for n in names)


def test_unknown_environment_lists_valid_names():
    with pytest.raises(RispError, match="quadrotor, cube, hand, rod"):
        get_environment("submarine")


@pytest.mark.parametrize("name", ENV_NAMES)
def test_sampler_is_deterministic_in_range_and_round_trips(name):
    env = get_environment(name)
    s1 = env.sample_states(np.random.default_rng(7), 300)
    s2 = env.sample_states(np.random.default_rng(7), 300)
    s3 = env.sample_states(np.random.default_rng(8), 300)
    assert s1.shape == (300, env.state_dim) and s1.dtype == np.float64
    np.testing.assert_array_equal(s1, s2)
    assert not np.allclose(s1, s3)
    assert np.all(s1 >= np.asarray(env.state_low) - 1e-12) and np.all(s1 <= np.asarray(env.state_high) + 1e-12)
    t = env.state_to_target(torch.from_numpy(s1))
    assert t.shape == (300, env.target_dim)
    back = env.target_to_state(t).numpy()
    np.testing.assert_allclose(back, s1, atol=1e-12)


def test_rigid_target_layout():
    env = get_environment("quadrotor")
    s = torch.tensor([[0.1, -0.2, 1.3, 0.4, -0.3, 0.2]], dtype=torch.float64)
    t = env.state_to_target(s)[0]
    angles = (0.4, -0.3, 0.2)
    expected = [0.1, -0.2, 1.3, *map(math.sin, angles), *map(math.cos, angles)]
    np.testing.assert_allclose(t.numpy(), expected, atol=1e-15)


def _all_vertices(env, states: np.ndarray) -> np.ndarray:
    return torch.cat([m.vertices for m in env.meshes(torch.from_numpy(states))], -2).numpy()


@pytest.mark.parametrize("name", ENV_NAMES)
def test_objects_always_in_view(name):
    """Every vertex of every sampled pose projects inside the image (the camera sees the whole object)."""
    env = get_environment(name)
    states = env.sample_states(np.random.default_rng(0), 1000)
    uv = project(env.camera, _all_vertices(env, states))
    assert not np.isnan(uv).any(), "a vertex is behind the camera"
    assert uv.min() > 0.0 and uv.max() < 1.0, (uv.min(), uv.max())


@pytest.mark.parametrize("name", ENV_NAMES)
def test_objects_stay_above_the_floor(name):
    env = get_environment(name)
    states = env.sample_states(np.random.default_rng(1), 500)
    assert _all_vertices(env, states)[..., 2].min() >= env.floor_height - 1e-9


def test_cube_sampler_reaches_the_floor():
    """The cube's z range starts at resting on the floor: the lowest sampled vertices come close to z = 0."""
    env = get_environment("cube")
    states = env.sample_states(np.random.default_rng(2), 2000)
    lowest = _all_vertices(env, states)[..., 2].min(-1)
    assert lowest.min() < 0.01 and lowest.min() >= -1e-9


@pytest.mark.parametrize("name", ENV_NAMES)
def test_mesh_vertices_gradcheck(name):
    """∂(vertices)/∂(state) by autograd matches finite differences (float64)."""
    env = get_environment(name)
    s0 = torch.from_numpy(env.sample_states(np.random.default_rng(3), 1)[0]).requires_grad_(True)
    step = 23 if name == "quadrotor" else 1  # subsample the 700 quadrotor vertices to keep it fast

    def verts(s):
        return torch.cat([m.vertices.reshape(-1, 3)[::step] for m in env.meshes(s)], 0).reshape(-1)

    assert torch.autograd.gradcheck(verts, (s0,), eps=1e-6, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("name", ENV_NAMES)
def test_meshes_are_closed_and_outward(name):
    """Every mesh part encloses a positive volume (faces wound counter-clockwise seen from outside)."""
    env = get_environment(name)
    s = torch.from_numpy(env.sample_states(np.random.default_rng(4), 1)[0])
    for m in env.meshes(s):
        assert m.faces.dtype == torch.int64 and m.faces.shape[1] == 3
        assert int(m.faces.max()) < m.vertices.shape[-2]
        assert signed_volume(m.vertices, m.faces) > 0, m.name


def test_primitive_volumes():
    v, f = box((0.1, 0.2, 0.3))
    assert signed_volume(v, f) == pytest.approx(8 * 0.1 * 0.2 * 0.3)
    v, f = cylinder(0.5, 0.0, 2.0, segments=64)
    assert signed_volume(v, f) == pytest.approx(math.pi * 0.25 * 2, rel=2e-3)
    assert tube_faces(3, 4).shape == (2 * 2 * 4 + 2 * 2, 3)


def test_meshes_batch_like_single_states():
    env = get_environment("hand")
    s = torch.from_numpy(env.sample_states(np.random.default_rng(5), 3))
    batched = env.meshes(s)
    for i in range(3):
        single = env.meshes(s[i])
        for mb, ms in zip(batched, single):
            torch.testing.assert_close(mb.vertices[i], ms.vertices)


def test_quadrotor_mesh_layout():
    """The PLY meshes follow the shared constants: rotor discs around ARM_LENGTH·(cos iπ/2, sin iπ/2)."""
    parts = quadrotor.body_meshes()
    assert set(parts) == {"frame", "rotors"}
    rv = parts["rotors"][0]
    for i in range(4):
        c = quadrotor.ARM_LENGTH * np.array([math.cos(i * math.pi / 2), math.sin(i * math.pi / 2)])
        near = rv[np.linalg.norm(rv[:, :2] - c, axis=1) <= quadrotor.ROTOR_RADIUS + 1e-6]
        assert len(near) > 20
        assert np.abs(near[:, 2] - quadrotor.ROTOR_HEIGHT).max() < 0.02
    extent = np.abs(np.concatenate([p[0] for p in parts.values()])[:, :2]).max()
    assert extent == pytest.approx(quadrotor.ARM_LENGTH + quadrotor.ROTOR_RADIUS, abs=1e-3)


def test_quadrotor_meshes_are_reproducible(tmp_path):
    """scenes/make_quadrotor.py regenerates the committed PLY files byte for byte."""
    import importlib.util

    script = os.path.join(quadrotor.SCENES_DIR, "make_quadrotor.py")
    spec = importlib.util.spec_from_file_location("make_quadrotor", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(str(tmp_path))
    for name in quadrotor.MESH_FILES.values():
        with open(tmp_path / name, "rb") as new, open(os.path.join(quadrotor.SCENES_DIR, name), "rb") as old:
            assert new.read() == old.read(), name


def test_quadrotor_pose_convention():
    """Yaw π/2 turns body +x (rotor 0) to world +y: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    s = torch.tensor([0.0, 0.0, 1.0, math.pi / 2, 0.0, 0.0], dtype=torch.float64)
    frame = quadrotor.meshes(s)[0].vertices.numpy()
    body = quadrotor.body_meshes()["frame"][0]
    i = int(np.argmax(body[:, 0]))  # the front-most body vertex
    np.testing.assert_allclose(frame[i], [-body[i, 1], body[i, 0], body[i, 2] + 1.0], atol=1e-12)


def test_hand_kinematics():
    zero = torch.zeros(13, dtype=torch.float64)
    links = hand.link_frames(zero)
    # index finger (links 2..4) points straight up from its base at zero angles
    tip = links[4][0] + hand.LINK_LENGTHS[1][2] * links[4][1][:, 2]
    straight = np.array(hand.FINGER_BASES[1]) + [0, 0, sum(hand.LINK_LENGTHS[1])]
    np.testing.assert_allclose(tip.numpy(), straight, atol=1e-12)
    for _, frame, _ in links:  # right-handed orthonormal frames
        np.testing.assert_allclose((frame.T @ frame).numpy(), np.eye(3), atol=1e-12)
        assert float(torch.det(frame)) == pytest.approx(1.0)
    bent = zero.clone()
    bent[2:5] = hand.JOINT_LIMIT  # flex the index finger
    links = hand.link_frames(bent)
    tip = links[4][0] + hand.LINK_LENGTHS[1][2] * links[4][1][:, 2]
    assert float(tip[1]) < -0.1  # a positive angle bends towards −y (towards the camera)


def test_rod_spline_through_sensors_and_fixed_ends():
    s = torch.from_numpy(rod.sample_states(np.random.default_rng(6), 4))
    z, _ = rod.spline_at(s, rod.SENSOR_X)
    torch.testing.assert_close(z, s)
    z_ends, _ = rod.spline_at(s, [-rod.ROD_LENGTH / 2, rod.ROD_LENGTH / 2])
    torch.testing.assert_close(z_ends, torch.full_like(z_ends, rod.REST_HEIGHT))
    _, _, d2W = rod.spline_matrices([-rod.ROD_LENGTH / 2, rod.ROD_LENGTH / 2])
    np.testing.assert_allclose(d2W, 0, atol=1e-9)  # natural spline: no curvature at the ends
    # the beam's cross-section centres lie on the centreline
    xs, zc, _ = rod.centreline(s)
    centres = rod.beam_vertices(s).reshape(4, rod.N_SECTIONS, 4, 3).mean(-2)
    torch.testing.assert_close(centres[..., 0], xs.expand(4, -1))
    torch.testing.assert_close(centres[..., 2], zc)


def test_rod_samples_are_smooth():
    """Sampled shapes are smooth (low sine modes), not independent noise: small second differences."""
    s = rod.sample_states(np.random.default_rng(9), 500)
    second = np.abs(np.diff(s, 2, axis=1)).max()
    assert second < 0.12
    assert s.min() < rod.REST_HEIGHT - 0.3  # sagging shapes are covered


def test_cube_rest_height_formula():
    s = cube.sample_states(np.random.default_rng(10), 50)
    s[:, 2] = 0.0
    v = cube.meshes(torch.from_numpy(s))[0].vertices.numpy()
    R = cube.rigid_pose(torch.from_numpy(s))[0].numpy()
    np.testing.assert_allclose(-v[..., 2].min(-1), cube.CUBE_SIDE / 2 * np.abs(R[:, 2, :]).sum(-1), atol=1e-12)
