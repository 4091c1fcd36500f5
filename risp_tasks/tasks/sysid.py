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


class FreeParameters:
    """The environment's identified parameters (IDENTIFIED) as leaf x ∈ [0, 1]^m, θ = low + (high − low)·x over
    the sampling ranges, the other parameters taken from ``base`` (1, P).  Shared by ``sysid`` and
    ``imitate --fit-params``."""

    def __init__(self, sim, base: torch.Tensor, x0: torch.Tensor):
        self.names = IDENTIFIED[sim.env]
        self.ranges = parameter_ranges(sim)
        self.low = torch.tensor([self.ranges[n][0] for n in self.names], dtype=torch.float64)
        self.high = torch.tensor([self.ranges[n][1] for n in self.names], dtype=torch.float64)
        self.idx = [sim.param_index(n) for n in self.names]
        self.base, self.x0 = base, x0
        self.x = x0.clone().requires_grad_(True)

    def __call__(self) -> torch.Tensor:
        """The full parameter row (1, P), differentiable w.r.t. x."""
        p = self.base.clone()
        p[0, self.idx] = self.low + (self.high - self.low) * self.x
        return p

    def project(self) -> None:
        self.x.clamp_(0.0, 1.0)

    def estimates(self) -> dict:
        def theta(x):
            return {n: float(v) for n, v in zip(self.names, (self.low + (self.high - self.low) * x).detach())}

        return {"parameters": theta(self.x), "initial_parameters": theta(self.x0),
                "ranges": {n: list(self.ranges[n]) for n in self.names}}


def bound_warnings(estimates: dict) -> list[str]:
    """One line per identified parameter that ended on an end of its range: the projection after each step
    (FreeParameters.project) held it there, so the video asked for a value at or beyond that end and the figure is a
    bound, not an estimate."""
    lines = []
    for name, value in estimates.get("parameters", {}).items():
        low, high = estimates.get("ranges", {}).get(name, (None, None))
        if low is None or high is None or not high > low:
            continue
        x = (value - low) / (high - low)
        if x <= 1e-9 or x >= 1 - 1e-9:
            end = "lower" if x <= 1e-9 else "upper"
            lines.append(f"{name} = {value:.4g} ended on the {end} end of its range [{low:g}, {high:g}] (the paper's "
                         f"sampling range, where the optimiser keeps it): the fit asked for "
                         f"{'less' if end == 'lower' else 'more'}, so read it as a bound, not an estimate")
    return lines


def build(ctx: Context) -> Problem:
    sim, names = ctx.sim, IDENTIFIED[ctx.sim.env]
    if ctx.cfg.init == "random":
        x0 = torch.from_numpy(ctx.rng.random(len(names)))
    elif ctx.cfg.init == "default":
        x0 = torch.full((len(names),), 0.5, dtype=torch.float64)
    else:
        raise RispError("sysid takes --init default or random")
    free = FreeParameters(sim, sim.default_params(), x0)
    if sim.action_dim and ctx.file_actions is None:
        raise RispError(f"sysid of the {sim.env} needs its commands: pass --actions A.csv")
    file_actions = None if ctx.file_actions is None else torch.from_numpy(ctx.file_actions)
    s0 = InitialState(ctx, fit=ctx.cfg.fit_initial_state)

    def states():
        p = free()
        actions = None if file_actions is None else to_sim_actions(sim, p, file_actions)
        return frame_states(sim, p, s0(), actions, ctx.n_source, ctx.k)

    return Problem(variables={"x": free.x, **s0.variables}, states=states,
                   estimates=lambda: {**free.estimates(), **s0.info()}, project=free.project, info=s0.info())
