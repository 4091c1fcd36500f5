"""What every task builder receives: the loaded model, simulator, reference and timeline."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .config import TaskConfig


@dataclass
class Context:
    cfg: TaskConfig
    env: object  # risp_data.envs.Environment
    sim: object  # risp_tasks.sims.base.Simulator
    predictor: object  # risp_train.predictor.RispPredictor
    frames: torch.Tensor  # (T_kept, r, r, 3) reference frames at the network's resolution, linear RGB
    keep: list[int]  # source-frame index of each kept frame (keep[0] == 0)
    n_source: int  # frames on the simulation timeline
    fps: float  # source frame rate (the simulation timeline)
    k: int  # simulator steps per source frame
    predicted: torch.Tensor  # (T_kept, S) N(reference) states
    predicted_targets: torch.Tensor  # (T_kept, T) N(reference) targets
    file_actions: np.ndarray | None  # (n_source, A) from --actions, file units
    truth: dict | None
    rng: np.random.Generator
