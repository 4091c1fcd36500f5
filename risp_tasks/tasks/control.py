"""``risp-task control``: actions that drive the system from a given initial state to a pictured state.

The reference is one image (the goal); the loss compares only the last of ``--horizon`` frames (at ``--fps``,
default 10) with it.  The initial state is ``--initial-state`` (JSON: {"state": [full simulator state]} or
{"env_state": [environment state]}) or the simulator's default state.
"""

from __future__ import annotations

import torch

from risp_data.errors import RispError

from . import imitate
from .context import Context
from .inputs import read_json
from .loop import Problem
from .simulate import initial_sim_state


def read_initial_state(path: str | None, sim) -> torch.Tensor:
    if path is None:
        return sim.default_state(1, torch.float64)
    data = read_json(path, "initial-state")
    if "state" in data:
        s = torch.tensor(data["state"], dtype=torch.float64).reshape(1, -1)
        if s.shape[1] != len(sim.state_names):
            raise RispError(f"{path}: 'state' must have {len(sim.state_names)} entries ({', '.join(sim.state_names[:6])}, …)")
    elif "env_state" in data:
        s = initial_sim_state(sim, torch.tensor(data["env_state"], dtype=torch.float64), None, 1.0)
    else:
        raise RispError(f"{path}: initial-state JSON needs the key 'state' or 'env_state'")
    if not torch.isfinite(s).all():
        raise RispError(f"{path}: initial state contains NaN/inf")
    return s


def build(ctx: Context) -> Problem:
    s0 = read_initial_state(ctx.cfg.initial_state, ctx.sim)
    problem = imitate.build(ctx, n_frames=ctx.cfg.horizon + 1, s0=s0)
    problem.frames = [ctx.cfg.horizon]  # only the final frame is compared with the goal image
    return problem
