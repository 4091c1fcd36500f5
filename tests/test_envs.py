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
    assert set(parts) == {"frame", "rotor_front", "rotor_left", "rotors"}
    rv = np.concatenate([parts[p][0] for p in ("rotor_front", "rotor_left", "rotors")])
    for i in range(4):
        c = quadrotor.ARM_LENGTH * np.array([math.cos(i * math.pi / 2), math.sin(i * math.pi / 2)])
        near = rv[np.linalg.norm(rv[:, :2] - c, axis=1) <= quadrotor.ROTOR_RADIUS + 1e-6]
        assert len(near) > 20
        assert np.abs(near[:, 2] - quadrotor.ROTOR_HEIGHT).max() < 0.02
    extent = np.abs(np.concatenate([p[0] for p in parts.values()])[:, :2]).max()
    assert extent == pytest.approx(quadrotor.ARM_LENGTH + quadrotor.ROTOR_RADIUS, abs=1e-3)


def _rotor_centres(vertices: np.ndarray) -> set[int]:
    """Indices i of the rotor axes ARM_LENGTH·(cos iπ/2, sin iπ/2) that the vertices lie around."""
    out = set()
    for i in range(4):
        c = quadrotor.ARM_LENGTH * np.array([math.cos(i * math.pi / 2), math.sin(i * math.pi / 2)])
        if (np.linalg.norm(vertices[:, :2] - c, axis=1) <= quadrotor.ROTOR_RADIUS + 1e-6).any():
            out.add(i)
    return out


def test_quadrotor_front_and_left_are_marked():
    """Front (+x) and left (+y) rotors are separate meshes with their own, mutually distinct fixed colours,
    so the rendered vehicle has no rotational symmetry (yaw is not ambiguous modulo 90°)."""
    from risp_data.envs.materials import FIXED_MATERIALS

    parts = quadrotor.body_meshes()
    assert _rotor_centres(parts["rotor_front"][0]) == {0}
    assert _rotor_centres(parts["rotor_left"][0]) == {1}
    assert _rotor_centres(parts["rotors"][0]) == {2, 3}
    colours = {quadrotor.MESH_MATERIALS[p] for p in ("rotor_front", "rotor_left", "rotors")}
    rgb = [np.asarray(FIXED_MATERIALS[c]) for c in colours]
    assert len(colours) == 3 and min(np.abs(a - b).max() for a in rgb for b in rgb if a is not b) > 0.3


def test_cube_target_is_the_continuous_6d_rotation():
    """The cube's target holds R's first two columns (continuous on SO(3), unlike Euler sin/cos); a perturbed
    6-vector maps back (Gram–Schmidt) to a nearby rotation, also across the gimbal-lock pitch ±π/2."""
    from risp_data.envs.rotations import euler_to_matrix

    env = get_environment("cube")
    assert env.target_names[3:] == ("r00", "r10", "r20", "r01", "r11", "r21")
    s = torch.tensor([[0.1, -0.1, 0.3, 2.0, math.pi / 2 - 1e-9, -1.0], [0.0, 0.0, 0.2, -3.0, 0.3, 3.1]],
                     dtype=torch.float64)
    t = env.state_to_target(s)
    R = euler_to_matrix(s[:, 3], s[:, 4], s[:, 5])
    torch.testing.assert_close(t[:, 3:6], R[:, :, 0])
    torch.testing.assert_close(t[:, 6:9], R[:, :, 1])
    noisy = t + 0.01 * torch.randn(t.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    back = env.target_to_state(noisy)
    R_back = euler_to_matrix(back[:, 3], back[:, 4], back[:, 5])
    angle = torch.arccos(((R_back * R).sum((-1, -2)) - 1).clamp(-2, 2) / 2)
    assert float(angle.max()) < 0.05  # radians: a small target error is a small rotation error


def _cube_rotations():
    """The 24 rotations of the cube: signed permutation matrices with determinant +1."""
    import itertools

    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            R = np.zeros((3, 3))
            R[list(range(3)), list(perm)] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return out


def test_cube_faces_carry_distinct_stickers():
    """Face value v carries one square sticker on its own face (numbered like a die: opposite faces sum to 7,
    1-2-3 counter-clockwise around their corner), six distinct colours, and no rotation of the cube but the
    identity maps every sticker onto the sticker of its colour."""
    from risp_data.envs.materials import FIXED_MATERIALS

    h = cube.CUBE_SIDE / 2
    meshes = {m.material: m for m in cube.meshes(torch.zeros(6, dtype=torch.float64))}
    normals = {}
    for value in range(1, 7):
        v = meshes[f"sticker{value}"].vertices.numpy()
        assert len(v) == 8 and len(meshes[f"sticker{value}"].faces) == 12  # one box
        axis = int(np.argmax(np.abs(v).min(0)))  # all sticker vertices are near the face plane of this axis
        assert np.all(np.abs(np.abs(v[:, axis]) - h) <= cube.STICKER_DEPTH + 1e-9)
        assert np.abs(v[:, axis]).max() == pytest.approx(h + cube.STICKER_RAISE)
        others = [a for a in range(3) if a != axis]
        np.testing.assert_allclose(np.abs(v[:, others]).max(0), cube.STICKER_HALF)  # a square, face-centred
        normals[value] = np.sign(v[0, axis]) * np.eye(3)[axis]
    for value in (1, 2, 3):
        np.testing.assert_array_equal(normals[value], -normals[7 - value])
    assert np.dot(np.cross(normals[1], normals[2]), normals[3]) > 0  # right-handed 1-2-3 corner
    colours = [np.asarray(FIXED_MATERIALS[f"sticker{v}"]) for v in range(1, 7)]
    assert min(np.abs(a - b).max() for i, a in enumerate(colours) for b in colours[i + 1:]) > 0.3
    symmetries = [R for R in _cube_rotations() if all(np.allclose(R @ normals[v], normals[v]) for v in normals)]
    assert len(_cube_rotations()) == 24 and len(symmetries) == 1 and np.allclose(symmetries[0], np.eye(3))


def _read_ply(path):
    import trimesh

    mesh = trimesh.load(path, process=False, force="mesh")
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def test_quadrotor_meshes_are_reproducible(tmp_path):
    """scenes/make_quadrotor.py regenerates the committed PLY files: same faces, same vertices up to the
    ASCII PLY's rounding (parsed, not byte for byte, so a new trimesh formatting does not break it)."""
    import importlib.util

    script = os.path.join(quadrotor.SCENES_DIR, "make_quadrotor.py")
    spec = importlib.util.spec_from_file_location("make_quadrotor", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(str(tmp_path))
    for name in quadrotor.MESH_FILES.values():
        v_new, f_new = _read_ply(tmp_path / name)
        v_old, f_old = _read_ply(os.path.join(quadrotor.SCENES_DIR, name))
        np.testing.assert_array_equal(f_new, f_old, err_msg=name)
        np.testing.assert_allclose(v_new, v_old, rtol=0, atol=1e-6, err_msg=name)


def test_quadrotor_in_memory_meshes_equal_the_ply_files(monkeypatch, tmp_path):
    """Without a scenes/ folder (a non-editable install) the meshes are built in memory and equal the PLYs."""
    from risp_data.envs import quadrotor_mesh

    built = quadrotor_mesh.build_meshes()
    assert set(built) == set(quadrotor.MESH_FILES)
    for part, name in quadrotor.MESH_FILES.items():
        v, f = _read_ply(os.path.join(quadrotor.SCENES_DIR, name))
        np.testing.assert_array_equal(built[part][1], f, err_msg=part)
        np.testing.assert_allclose(built[part][0], v, rtol=0, atol=1e-6, err_msg=part)
    # the loader falls back to the in-memory build when the folder is missing
    quadrotor.body_meshes.cache_clear()
    monkeypatch.setattr(quadrotor, "SCENES_DIR", str(tmp_path / "no-scenes-here"))
    try:
        fallback = quadrotor.body_meshes()
        for part in quadrotor.MESH_FILES:
            np.testing.assert_array_equal(fallback[part][0], built[part][0])
            np.testing.assert_array_equal(fallback[part][1], built[part][1])
    finally:
        quadrotor.body_meshes.cache_clear()


def test_quadrotor_pose_convention():
    """Yaw π/2 turns body +x (rotor 0) to world +y: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    s = torch.tensor([0.0, 0.0, 1.0, math.pi / 2, 0.0, 0.0], dtype=torch.float64)
    frame = quadrotor.meshes(s)[0].vertices.numpy()
    body = quadrotor.body_meshes()["frame"][0]
    i = int(np.argmax(body[:, 0]))  # the front-most body vertex
    np.testing.assert_allclose(frame[i], [-body[i, 1], body[i, 0], body[i, 2] + 1.0], atol=1e-12)


def _random_angles(n=200, seed=13, pitch_limit=math.pi):
    gen = torch.Generator().manual_seed(seed)
    yaw = (2 * torch.rand(n, generator=gen, dtype=torch.float64) - 1) * math.pi
    pitch = (2 * torch.rand(n, generator=gen, dtype=torch.float64) - 1) * pitch_limit
    roll = (2 * torch.rand(n, generator=gen, dtype=torch.float64) - 1) * math.pi
    return yaw, pitch, roll


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def test_euler_to_matrix_is_rz_ry_rx_on_random_angles():
    from risp_data.envs.rotations import euler_to_matrix

    yaw, pitch, roll = _random_angles()
    R = euler_to_matrix(yaw, pitch, roll).numpy()
    for i in range(len(yaw)):
        expected = _rz(float(yaw[i])) @ _ry(float(pitch[i])) @ _rx(float(roll[i]))
        np.testing.assert_allclose(R[i], expected, atol=1e-13)


def test_quaternion_and_matrix_conventions_agree():
    from risp_data.envs.rotations import euler_to_matrix, euler_to_quat, quat_to_matrix

    yaw, pitch, roll = _random_angles(seed=14)
    q = euler_to_quat(yaw, pitch, roll)
    torch.testing.assert_close(q.norm(dim=-1), torch.ones_like(yaw))
    torch.testing.assert_close(quat_to_matrix(q), euler_to_matrix(yaw, pitch, roll), rtol=0, atol=1e-13)
    torch.testing.assert_close(quat_to_matrix(-q), euler_to_matrix(yaw, pitch, roll), rtol=0, atol=1e-13)


def test_euler_round_trips_for_pitch_within_90_degrees():
    from risp_data.envs.rotations import euler_to_matrix, euler_to_quat, matrix_to_euler, quat_to_euler

    yaw, pitch, roll = _random_angles(seed=15, pitch_limit=0.99 * math.pi / 2)
    expected = torch.stack([yaw, pitch, roll], -1)
    torch.testing.assert_close(matrix_to_euler(euler_to_matrix(yaw, pitch, roll)), expected, rtol=0, atol=1e-10)
    q = euler_to_quat(yaw, pitch, roll)
    torch.testing.assert_close(quat_to_euler(q), expected, rtol=0, atol=1e-10)
    torch.testing.assert_close(quat_to_euler(-q), expected, rtol=0, atol=1e-10)  # q and −q: same rotation
    # |pitch| > π/2 maps to the equivalent triple with |pitch| < π/2 (same matrix)
    yaw, pitch, roll = _random_angles(seed=16)
    back = matrix_to_euler(euler_to_matrix(yaw, pitch, roll))
    assert float(back[:, 1].abs().max()) <= math.pi / 2 + 1e-12
    torch.testing.assert_close(euler_to_matrix(*back.unbind(-1)), euler_to_matrix(yaw, pitch, roll), rtol=0, atol=1e-12)


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


def test_hand_phalanges_are_marked():
    """Every finger's last link is red, a three-link finger's middle link white, the proximal links and the
    palm take ψ's object colour: the joints between links show at 64×64."""
    from risp_data.envs.materials import FIXED_MATERIALS

    materials = {m.name: m.material for m in hand.meshes(torch.zeros(13, dtype=torch.float64))}
    assert materials.pop("palm") == "object"
    expected = {}
    for finger, n in zip(hand.FINGERS, hand.JOINTS_PER_FINGER):
        names = [f"link_{finger}_{k}" for k in range(n)]
        expected.update({names[0]: "object", names[-1]: "phalanx_distal"})
        if n == 3:
            expected[names[1]] = "phalanx_middle"
    assert materials == expected
    middle, distal = (np.asarray(FIXED_MATERIALS[m]) for m in ("phalanx_middle", "phalanx_distal"))
    assert np.abs(middle - distal).max() > 0.3


def test_rod_spline_through_sensors_and_fixed_ends():
    s = torch.from_numpy(rod.sample_states(np.random.default_rng(6), 4))
    z, _ = rod.spline_at(s, rod.SENSOR_X)
    torch.testing.assert_close(z, s)
    z_ends, _ = rod.spline_at(s, [-rod.ROD_LENGTH / 2, rod.ROD_LENGTH / 2])
    torch.testing.assert_close(z_ends, torch.full_like(z_ends, rod.REST_HEIGHT))
    _, dW, _ = rod.spline_matrices([-rod.ROD_LENGTH / 2, rod.ROD_LENGTH / 2])
    np.testing.assert_allclose(dW, 0, atol=1e-9)  # clamped spline: zero slope at both ends, like the simulator
    _, dz_ends = rod.spline_at(s, [-rod.ROD_LENGTH / 2, rod.ROD_LENGTH / 2])
    torch.testing.assert_close(dz_ends, torch.zeros_like(dz_ends))
    # C² at the interior knots: left and right second derivatives agree, cubic pieces are exact
    x = np.asarray(rod.KNOTS_X[1:-1])
    _, _, d2_left = rod.spline_matrices(x - 1e-9)
    _, _, d2_right = rod.spline_matrices(x + 1e-9)
    np.testing.assert_allclose(d2_left, d2_right, atol=1e-5)
    # the beam's cross-section centres lie on the centreline
    xs, zc, _ = rod.centreline(s)
    centres = rod.beam_vertices(s).reshape(4, rod.N_SECTIONS, 4, 3).mean(-2)
    torch.testing.assert_close(centres[..., 0], xs.expand(4, -1))
    torch.testing.assert_close(centres[..., 2], zc)


def test_rod_samples_are_smooth():
    """Sampled shapes are smooth (low sine modes), not independent noise: small second differences."""
    s = rod.sample_states(np.random.default_rng(9), 500)
    second = np.abs(np.diff(s, 2, axis=1)).max()
    assert second < 0.2  # independent uniform noise over the 1.2 m range would reach ~2
    assert s.min() < rod.REST_HEIGHT - 0.5  # deep sags are covered
    assert s.max() > rod.REST_HEIGHT + 0.3  # and rods pushed up


def test_rod_spline_is_differentiable_in_torch():
    """The clamped spline is applied as a torch linear map: exact gradients w.r.t. the sensor heights."""
    s = torch.from_numpy(rod.sample_states(np.random.default_rng(12), 2)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: torch.cat(rod.spline_at(t, [-0.45, -0.1, 0.2, 0.47]), -1), (s,))


def test_cube_rest_height_formula():
    s = cube.sample_states(np.random.default_rng(10), 50)
    s[:, 2] = 0.0
    v = cube.meshes(torch.from_numpy(s))[0].vertices.numpy()
    R = cube.rigid_pose(torch.from_numpy(s))[0].numpy()
    np.testing.assert_allclose(-v[..., 2].min(-1), cube.CUBE_SIDE / 2 * np.abs(R[:, 2, :]).sum(-1), atol=1e-12)


def test_euler_angles_have_finite_gradients_at_gimbal_lock():
    """A cube resting on a side face has pitch ±π/2: there |R₂₀| = 1, asin' is infinite and atan2's gradient
    0/0 (R₀₀ = R₁₀ = 0).  The gradient of anything smooth computed through the angles must stay finite (a NaN made
    whole table cells fail), and the angles must stay what they were away from the pole."""
    import math

    import torch

    from risp_data.envs.rotations import euler_to_matrix, matrix_to_euler, quat_to_euler, quat_to_matrix

    for pitch in (math.pi / 2, -math.pi / 2):
        R = euler_to_matrix(*(torch.tensor(a, dtype=torch.float64) for a in (0.3, pitch, 0.2)))
        R = torch.where(R.abs() < 1e-12, 0.0, torch.where((R.abs() - 1).abs() < 1e-12, R.sign(), R))  # on the pole
        assert float(R[0, 0]) == float(R[1, 0]) == 0.0 and abs(float(R[2, 0])) == 1.0
        R.requires_grad_(True)
        angles = matrix_to_euler(R)
        assert abs(abs(float(angles[1].detach())) - math.pi / 2) < 1e-7
        (torch.sin(angles) + torch.cos(angles)).sum().backward()
        assert torch.isfinite(R.grad).all(), R.grad
    g = torch.Generator().manual_seed(0)
    q = torch.nn.functional.normalize(torch.randn(200, 4, generator=g, dtype=torch.float64), dim=-1)
    R = quat_to_matrix(q)
    reference = torch.stack([torch.atan2(R[:, 1, 0], R[:, 0, 0]), torch.asin(-R[:, 2, 0]),
                             torch.atan2(R[:, 2, 1], R[:, 2, 2])], -1)
    assert torch.allclose(quat_to_euler(q), reference, atol=1e-12, rtol=0)
