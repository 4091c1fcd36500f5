"""The environment interface shared by rendering (risp_data), training and tasks (risp_tasks).

An environment describes *what is seen*: the state vector, the network target vector, a differentiable
map from states to world-space triangle meshes, a state sampler, and one fixed camera.  The physics of
the same system lives in ``risp_tasks.sims`` and maps its full simulator state onto this state vector.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch


@dataclass(frozen=True)
class Mesh:
    """One world-space triangle mesh. ``vertices`` (..., V, 3) carries gradients w.r.t. the state."""

    name: str  # unique within the environment, e.g. "body", "rotor0", "rod"
    vertices: torch.Tensor  # (..., V, 3)
    faces: torch.Tensor  # (F, 3) int64, fixed topology
    material: str  # "object" (uses the object reflectance ψ) or another named material


@dataclass(frozen=True)
class Camera:
    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    fov: float  # degrees, horizontal


@dataclass(frozen=True)
class Environment:
    name: str
    state_names: tuple[str, ...]
    target_names: tuple[str, ...]
    state_low: tuple[float, ...]  # documented sampler range (inclusive low)
    state_high: tuple[float, ...]
    camera: Camera
    # states (..., S) float tensor -> targets (..., T)
    state_to_target: Callable[[torch.Tensor], torch.Tensor]
    # targets (..., T) -> states (..., S)  (e.g. atan2 of sin/cos); inverse of state_to_target on its range
    target_to_state: Callable[[torch.Tensor], torch.Tensor]
    # states (..., S) -> list of world-space meshes, differentiable w.r.t. states
    meshes: Callable[[torch.Tensor], list[Mesh]]
    # (rng, n) -> (n, S) float64 states; covers the poses the simulator produces, object always in view
    sample_states: Callable[[np.random.Generator, int], np.ndarray]
    floor_height: float | None = 0.0  # z of the floor plane, None when there is no floor
    description: str = ""

    @property
    def state_dim(self) -> int:
        return len(self.state_names)

    @property
    def target_dim(self) -> int:
        return len(self.target_names)
