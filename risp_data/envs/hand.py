"""Hand: a fixed palm with five fingers and 13 revolute (flexion) joints, each in [−π/4, π/4].

State (13): joint angles [rad] in the order of JOINT_NAMES.  Target (13): the same angles.
Geometry constants are shared with the simulator (risp_tasks.sims.hand).  The palm is a box centred at
PALM_CENTER; finger f's first joint sits at FINGER_BASES[f] (palm frame = world frame, palm fixed);
each finger is a chain of links of the listed lengths, all joints of a finger flex about the same
axis FINGER_AXES[f]; at zero angles every finger points along FINGER_DIRECTIONS[f].
"""

FINGERS = ("thumb", "index", "middle", "ring", "little")
JOINTS_PER_FINGER = (2, 3, 3, 3, 2)  # 13 joints in total
JOINT_NAMES = tuple(
    f"{f}_{j}" for f, n in zip(FINGERS, JOINTS_PER_FINGER) for j in range(n)
)
JOINT_LIMIT = 0.7853981633974483  # π/4
PALM_CENTER = (0.0, 0.0, 0.5)
PALM_HALF_EXTENTS = (0.2, 0.05, 0.2)  # x (width), y (thickness), z (height); fingers point up (+z)
FINGER_BASES = (
    (-0.22, 0.0, 0.40),  # thumb, on the palm's −x side, pointing sideways-up
    (-0.15, 0.0, 0.70),
    (-0.05, 0.0, 0.70),
    (0.05, 0.0, 0.70),
    (0.15, 0.0, 0.70),
)
FINGER_DIRECTIONS = ((-0.7071067811865476, 0.0, 0.7071067811865476), (0, 0, 1), (0, 0, 1), (0, 0, 1), (0, 0, 1))
FINGER_AXES = ((1.0, 0.0, 0.0),) * 5  # flexion about world x: a positive angle bends the finger towards −y
LINK_LENGTHS = (
    (0.12, 0.10),
    (0.14, 0.10, 0.08),
    (0.16, 0.11, 0.08),
    (0.14, 0.10, 0.08),
    (0.10, 0.08),
)
LINK_RADIUS = 0.03  # m, finger thickness (half)

# --- Rendering (risp_data): forward kinematics, meshes, camera, sampler -------------------------------

import numpy as np  # noqa: E402
import torch  # noqa: E402

from .base import Camera, Environment, Mesh  # noqa: E402
from .meshes import box, identity, mat3_mul, transform  # noqa: E402

STATE_LOW = (-JOINT_LIMIT,) * len(JOINT_NAMES)
STATE_HIGH = (JOINT_LIMIT,) * len(JOINT_NAMES)
# Seen from the −y side (fingers flex towards the camera), a little from the right and above.
CAMERA = Camera(origin=(1.1, -2.0, 1.3), target=(-0.05, 0.0, 0.66), up=(0.0, 0.0, 1.0), fov=25.0)
JOINT_OVERLAP = 0.5 * LINK_RADIUS  # links extend this far past each joint so bent fingers show no gaps


def _rest_frame(f: int) -> np.ndarray:
    """Right-handed columns (a, b, u): u = finger direction, b = the flexion direction (axis × u,
    normalised), a = b × u."""
    u = np.asarray(FINGER_DIRECTIONS[f], np.float64)
    u /= np.linalg.norm(u)
    b = np.cross(np.asarray(FINGER_AXES[f], np.float64), u)
    b /= np.linalg.norm(b)
    return np.stack([np.cross(b, u), b, u], -1)


def _axis_rotation(axis, angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues: rotation by ``angle`` (...) about the fixed unit ``axis`` -> (..., 3, 3)."""
    k = torch.as_tensor(np.asarray(axis, np.float64) / np.linalg.norm(axis), dtype=angle.dtype)
    K = torch.zeros(3, 3, dtype=angle.dtype)
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -k[2], k[1], k[2], -k[0], -k[1], k[0]
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return torch.eye(3, dtype=angle.dtype) + s * K + (1 - c) * mat3_mul(K, K)


def link_frames(states: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor, float]]:
    """Forward kinematics: for every link (finger order, base to tip) its joint position (..., 3),
    world frame (..., 3, 3) = Rot(axis_f, θ_1 + … + θ_k) · F_f^rest and length.  The next joint sits at
    p_{k+1} = p_k + L_k · (frame_k e_3)."""
    out, j = [], 0
    for f, n in enumerate(JOINTS_PER_FINGER):
        rest = torch.as_tensor(_rest_frame(f), dtype=states.dtype)
        p = torch.as_tensor(FINGER_BASES[f], dtype=states.dtype).expand(*states.shape[:-1], 3)
        angle = torch.zeros_like(states[..., 0])
        for k in range(n):
            angle = angle + states[..., j]
            frame = mat3_mul(_axis_rotation(FINGER_AXES[f], angle), rest)
            out.append((p, frame, LINK_LENGTHS[f][k]))
            p = p + LINK_LENGTHS[f][k] * frame[..., :, 2]
            j += 1
    return out


def meshes(states: torch.Tensor) -> list[Mesh]:
    """The fixed palm box and one box per finger link (cross-section 2·LINK_RADIUS square; materials by
    :func:`link_material`)."""
    pv, pf = box(PALM_HALF_EXTENTS, PALM_CENTER)
    out = [Mesh("palm", pv.to(states.dtype).expand(*states.shape[:-1], -1, -1), pf, "object")]
    for i, (p, frame, length) in enumerate(link_frames(states)):
        half = (LINK_RADIUS, LINK_RADIUS, length / 2 + JOINT_OVERLAP)
        v, f = box(half, (0.0, 0.0, length / 2))
        out.append(Mesh(f"link_{JOINT_NAMES[i]}", transform(v, frame, p), f, link_material(i)))
    return out


def link_material(i: int) -> str:
    """Material of link i (JOINT_NAMES order): every finger's last link is ``phalanx_distal`` (red), a
    three-link finger's middle link ``phalanx_middle`` (white), the proximal links take the object colour ψ.
    Why: in one colour the joints between links are invisible at 64×64, and a network read the thumb and the
    proximal joints 9 % worse over 3 seeds (docs/RESULTS.md §Identifiable marks, revisited)."""
    f, k = 0, i
    while k >= JOINTS_PER_FINGER[f]:
        k -= JOINTS_PER_FINGER[f]
        f += 1
    if k == JOINTS_PER_FINGER[f] - 1:
        return "phalanx_distal"
    return "phalanx_middle" if k == 1 else "object"


def sample_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 13) joint angles uniform in [−π/4, π/4] (the joint limits)."""
    return rng.uniform(-JOINT_LIMIT, JOINT_LIMIT, size=(int(n), len(JOINT_NAMES)))


def make_environment() -> Environment:
    return Environment(
        name="hand",
        state_names=JOINT_NAMES,
        target_names=JOINT_NAMES,
        state_low=STATE_LOW,
        state_high=STATE_HIGH,
        camera=CAMERA,
        state_to_target=identity,
        target_to_state=identity,
        meshes=meshes,
        sample_states=sample_states,
        floor_height=0.0,
        description="fixed palm with five fingers and 13 revolute flexion joints",
    )
