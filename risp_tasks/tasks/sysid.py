"""``risp-task sysid``: the system parameters that reproduce a video (paper Sec. 5.3).

Identified parameters (paper's ranges): quadrotor mass [2.8, 3.2) kg, cube log10 k_n [5.5, 6.5), hand per-finger
joint stiffness [0, 1), rod log10 E [4, 7).  Each is optimised in normalised coordinates x ∈ [0, 1],
θ = low + (high − low)·x (clamped after every step), starting from the middle of the range (``--init default``)
or a seeded uniform draw (``--init random``).  The initial state comes from the network's estimates of the
first two frames (docs/tasks.md §Initial state) — fixed, or with ``--fit-initial-state`` identified jointly with
the parameters (:class:`~risp_tasks.tasks.simulate.InitialState`); actions from ``--actions``.
"""

from __future__ import annotations

import torch

from risp_data.errors import RispError

from .context import Context
from .loop import Problem
from .simulate import InitialState, frame_states, to_sim_actions

IDENTIFIED = {"quadrotor": ("mass",), "cube": ("log10_kn",),
              "hand": tuple(f"stiffness_{f}" for f in ("thumb", "index", "middle", "ring", "little")),
              "rod": ("log10_E",)}


def parameter_ranges(sim) -> dict[str, tuple[float, float]]:
    ranges = dict(zip(sim.spec.base_param_names, sim.spec.base_param_ranges))
    return {name: ranges[name] for name in IDENTIFIED[sim.env]}


def build(ctx: Context) -> Problem:
    sim, names = ctx.sim, IDENTIFIED[ctx.sim.env]
    ranges = parameter_ranges(sim)
    low = torch.tensor([ranges[n][0] for n in names], dtype=torch.float64)
    high = torch.tensor([ranges[n][1] for n in names], dtype=torch.float64)
    if ctx.cfg.init == "random":
        x0 = torch.from_numpy(ctx.rng.random(len(names)))
    elif ctx.cfg.init == "default":
        x0 = torch.full((len(names),), 0.5, dtype=torch.float64)
    else:
        raise RispError("sysid takes --init default or random")
    x = x0.clone().requires_grad_(True)
    idx = [sim.param_index(n) for n in names]
    base = sim.default_params()
    if sim.action_dim and ctx.file_actions is None:
        raise RispError(f"sysid of the {sim.env} needs its commands: pass --actions A.csv")
    file_actions = None if ctx.file_actions is None else torch.from_numpy(ctx.file_actions)
    s0 = InitialState(ctx, fit=ctx.cfg.fit_initial_state)

    def params():
        theta = low + (high - low) * x
        p = base.clone()
        p[0, idx] = theta
        return p

    def states():
        p = params()
        actions = None if file_actions is None else to_sim_actions(sim, p, file_actions)
        return frame_states(sim, p, s0(), actions, ctx.n_source, ctx.k)

    def project():
        x.clamp_(0.0, 1.0)

    def estimates():
        theta = (low + (high - low) * x).detach()
        return {"parameters": {n: float(v) for n, v in zip(names, theta)},
                "initial_parameters": {n: float(v) for n, v in zip(names, low + (high - low) * x0)},
                "ranges": {n: list(ranges[n]) for n in names}, **s0.info()}

    return Problem(variables={"x": x, **s0.variables}, states=states, estimates=estimates, project=project,
                   info=s0.info())
