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
        s = _numbers(data["state"], path, "state").reshape(1, -1)
        if s.shape[1] != len(sim.state_names):
            raise RispError(f"{path}: 'state' must have {len(sim.state_names)} entries ({', '.join(sim.state_names[:6])}, …)")
    elif "env_state" in data:
        from risp_data.envs import get_environment

        if sim.env == "rod":  # initial_sim_state starts the rod at rest: sensor heights cannot set its 360 values
            raise RispError(f"{path}: the rod's initial state cannot be given as 'env_state' (sensor heights); "
                            f"give 'state' ({len(sim.state_names)} values) or leave --initial-state out (rest)")

        n_env = len(get_environment(sim.env).state_names)
        e = _numbers(data["env_state"], path, "env_state").reshape(-1)
        if e.numel() != n_env:
            raise RispError(f"{path}: 'env_state' must have {n_env} entries, got {e.numel()}")
        s = initial_sim_state(sim, e, None, 1.0)
    else:
        raise RispError(f"{path}: initial-state JSON needs the key 'state' or 'env_state'")
    if not torch.isfinite(s).all():
        raise RispError(f"{path}: initial state contains NaN/inf")
    return s


def initial_state_warning(sim, s0: torch.Tensor, path: str) -> str | None:
    """A warning (for result.json's ``warnings``, printed at the end) when the given initial state lies outside
    the box the networks' training states were drawn from: the network never saw the system there, so its reading
    of the rendered frames (the `render` loss) is an extrapolation. None when it lies inside
    (risp_tasks.tasks.reference.outside_sampled_states' tolerance)."""
    from .reference import outside_sampled_states

    env_state = sim.to_env_state(s0.reshape(1, -1)).detach().numpy()
    outside = outside_sampled_states(sim.env, env_state)
    if not outside["fraction"] > 0:
        return None
    names = ", ".join(outside["states"])
    return (f"{path}: the initial state's {names} lie(s) outside the range the networks are trained on: "
            "the network's readings near it are extrapolations (docs/tasks.md §Reference videos)")


def _numbers(value, path: str, key: str) -> torch.Tensor:
    """A flat list of numbers as float64, or one error line (strings, nested or ragged lists)."""
    try:
        return torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError, OverflowError):  # OverflowError: an integer beyond float's range
        raise RispError(f"{path}: {key!r} must be a list of numbers") from None


def build(ctx: Context) -> Problem:
    s0 = read_initial_state(ctx.cfg.initial_state, ctx.sim)
    problem = imitate.build(ctx, n_frames=ctx.cfg.horizon + 1, s0=s0)
    problem.frames = [ctx.cfg.horizon]  # only the final frame is compared with the goal image
    if ctx.cfg.initial_state is not None:
        problem.info["warnings"] = [w for w in [initial_state_warning(ctx.sim, s0, ctx.cfg.initial_state)] if w]
    return problem
