"""Rod: a deformable beam with both ends fixed, seen from the side.

State (10): world z [m] of the rod's centreline at the 10 sensors SENSOR_X (evenly spaced interior
points; the ends at ±ROD_LENGTH/2 are fixed at REST_HEIGHT).  Target (10): the same.
Geometry/material constants are shared with the simulator (risp_tasks.sims.rod).
"""

ROD_LENGTH = 1.0  # m, along world x, from −0.5 to +0.5
ROD_WIDTH = 0.2  # m, along world y
ROD_THICKNESS = 0.1  # m, along world z
ROD_DENSITY = 500.0  # kg/m³
REST_HEIGHT = 1.0  # m, z of the undeformed centreline
N_SENSORS = 10
SENSOR_X = tuple(-0.5 + ROD_LENGTH * (i + 1) / (N_SENSORS + 1) for i in range(N_SENSORS))

# --- Rendering (risp_data): spline centreline, swept beam, end posts, camera, sampler ---------------

import math  # noqa: E402
from functools import lru_cache  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from .base import Camera, Environment, Mesh  # noqa: E402
from .meshes import box_between, identity, tube_faces  # noqa: E402

SENSOR_NAMES = tuple(f"z{i}" for i in range(N_SENSORS))
# Rendered range of every sensor height.  It covers the simulator's equilibria for log10 E >= 5 with
# |force| <= 500 N and for log10 E >= 4 with |force| <= 100 N (docs/models/rod.md, "Rendered range").
SENSOR_LOW, SENSOR_HIGH = REST_HEIGHT - 0.7, REST_HEIGHT + 0.5
STATE_LOW = (SENSOR_LOW,) * N_SENSORS
STATE_HIGH = (SENSOR_HIGH,) * N_SENSORS
KNOTS_X = (-ROD_LENGTH / 2, *SENSOR_X, ROD_LENGTH / 2)  # 12 spline knots: fixed ends + sensors
N_SECTIONS = 45  # cross-sections along the beam (rings of the swept mesh)
POST_HALF_WIDTH = 0.05  # m, end posts (x extent 2·0.05, y extent as below)
POST_HALF_DEPTH = 0.15
POST_TOP = REST_HEIGHT + 0.15
CAMERA = Camera(origin=(0.35, -2.9, 1.45), target=(0.0, 0.0, 0.8), up=(0.0, 0.0, 1.0), fov=38.0)
# Smooth sampled shapes: z(ξ) = REST_HEIGHT + Σ_m a_m sin(π ξ) sin(m π ξ), ξ = (x + L/2)/L ∈ [0, 1]:
# each mode vanishes with zero slope at both ends, like the clamped-clamped rod of the simulator.
MODE_AMPLITUDES = ((-0.75, 0.55), (-0.2, 0.2), (-0.1, 0.1))


def spline_matrices(xs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The clamped cubic spline through the 12 knots, as linear maps evaluated at ``xs``.

    Returns (W, dW, d2W), each (len(xs), 12), with z(xs) = W · z_knots, z'(xs) = dW · z_knots and
    z''(xs) = d2W · z_knots for the clamped cubic spline (C², cubic between knots, z' = 0 at both
    ends, like the simulator's clamped rod) through (KNOTS_X, z_knots).  The spline is linear in the
    knot values, so its weights are the splines of the unit vectors (computed once with scipy; the map
    itself is applied in torch, so the rendered mesh stays differentiable in the state).
    """
    from scipy.interpolate import CubicSpline

    spline = CubicSpline(np.asarray(KNOTS_X), np.eye(len(KNOTS_X)), axis=0, bc_type="clamped")
    xs = np.asarray(xs, np.float64)
    return spline(xs), spline(xs, 1), spline(xs, 2)


@lru_cache(maxsize=None)
def _section_matrices(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs = np.linspace(-ROD_LENGTH / 2, ROD_LENGTH / 2, n)
    W, dW, _ = spline_matrices(xs)
    return xs, W, dW


def spline_at(states: torch.Tensor, xs) -> tuple[torch.Tensor, torch.Tensor]:
    """(z (..., n), dz/dx (..., n)) of the centreline spline through (−L/2, REST), the sensors
    (SENSOR_X, states) and (L/2, REST), at the points ``xs`` (n,)."""
    W, dW, _ = spline_matrices(xs)
    return _apply(states, W, dW)


def _apply(states: torch.Tensor, W: np.ndarray, dW: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    ends = torch.full_like(states[..., :1], REST_HEIGHT)
    knots = torch.cat([ends, states, ends], -1)
    W, dW = torch.as_tensor(W, dtype=states.dtype), torch.as_tensor(dW, dtype=states.dtype)
    return knots @ W.T, knots @ dW.T


def centreline(states: torch.Tensor, n: int = N_SECTIONS) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(xs (n,), z (..., n), dz/dx (..., n)) at n evenly spaced points from −L/2 to L/2."""
    xs, W, dW = _section_matrices(n)
    z, dz = _apply(states, W, dW)
    return torch.as_tensor(xs, dtype=states.dtype), z, dz


def beam_vertices(states: torch.Tensor) -> torch.Tensor:
    """Swept box section: at each centreline point c = (x, 0, z(x)), the 4 corners c ± w/2 ŷ ± h/2 n̂,
    with n̂ = (−z', 0, 1)/√(1 + z'²) the centreline normal in the xz plane.  (..., N_SECTIONS·4, 3)."""
    xs, z, dz = centreline(states)
    norm = torch.sqrt(1 + dz * dz)
    nx, nz = -dz / norm, 1 / norm
    cx = xs.expand_as(z)
    w, h = ROD_WIDTH / 2, ROD_THICKNESS / 2
    corners = []
    # counter-clockwise about +x (the sweep direction): (y, n) = (−,−), (+,−), (+,+), (−,+)
    for sy, sn in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        corners.append(torch.stack([cx + sn * h * nx, torch.full_like(z, sy * w), z + sn * h * nz], -1))
    return torch.stack(corners, -2).flatten(-3, -2)


def meshes(states: torch.Tensor) -> list[Mesh]:
    """The deformed beam (material "object") and the two fixed end posts (material "post")."""
    out = [Mesh("rod", beam_vertices(states), tube_faces(N_SECTIONS, 4), "object")]
    batch = states.shape[:-1]
    for side, sign in (("left", -1.0), ("right", 1.0)):
        x0 = sign * ROD_LENGTH / 2
        x1 = x0 + sign * 2 * POST_HALF_WIDTH
        v, f = box_between((min(x0, x1), -POST_HALF_DEPTH, 0.0), (max(x0, x1), POST_HALF_DEPTH, POST_TOP))
        out.append(Mesh(f"post_{side}", v.to(states.dtype).expand(*batch, -1, -1), f, "post"))
    return out


def sample_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 10) smooth shapes: z_i = REST + Σ_{m=1..3} a_m sin(π ξ_i) sin(m π ξ_i), a_m uniform in
    MODE_AMPLITUDES; a shape leaving [SENSOR_LOW, SENSOR_HIGH] = [REST − 0.7, REST + 0.5] has its
    deviation from REST scaled down to fit."""
    n = int(n)
    xi = (np.asarray(SENSOR_X) + ROD_LENGTH / 2) / ROD_LENGTH
    modes = np.stack([np.sin(math.pi * xi) * np.sin((m + 1) * math.pi * xi) for m in range(len(MODE_AMPLITUDES))])
    lo, hi = np.asarray(MODE_AMPLITUDES).T
    a = rng.uniform(lo, hi, size=(n, len(MODE_AMPLITUDES)))
    dev = a @ modes
    scale = np.ones(n)
    low_dev, high_dev = dev.min(1), dev.max(1)
    scale = np.minimum(scale, np.where(low_dev < SENSOR_LOW - REST_HEIGHT, (SENSOR_LOW - REST_HEIGHT) / low_dev, 1))
    scale = np.minimum(scale, np.where(high_dev > SENSOR_HIGH - REST_HEIGHT, (SENSOR_HIGH - REST_HEIGHT) / high_dev, 1))
    return REST_HEIGHT + dev * scale[:, None]


def make_environment() -> Environment:
    return Environment(
        name="rod",
        state_names=SENSOR_NAMES,
        target_names=SENSOR_NAMES,
        state_low=STATE_LOW,
        state_high=STATE_HIGH,
        camera=CAMERA,
        state_to_target=identity,
        target_to_state=identity,
        meshes=meshes,
        sample_states=sample_states,
        floor_height=0.0,
        description="deformable beam with both ends fixed in two posts, seen from the side",
    )
