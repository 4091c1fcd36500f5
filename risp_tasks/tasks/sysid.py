"""``risp-task sysid``: the system parameters that reproduce a video (paper Sec. 5.3).

Identified parameters (paper's ranges): quadrotor mass [2.8, 3.2) kg, cube log10 k_n [5.5, 6.5), hand per-finger
joint stiffness [0, 1), rod log10 E [4, 7).  Each is optimised in normalised coordinates x ∈ [0, 1],
θ = low + (high − low)·x (clamped after every step), starting from the middle of the range (``--init default``),
a seeded uniform draw (``--init random``) or the best point of a coarse scan of the state loss over the range
(``--init scan``: :func:`scan_start`, a global start for the local descent).  The initial state comes from the
network's estimates of the first two frames (docs/tasks.md §Initial state) — fixed, or with
``--fit-initial-state`` identified jointly with the parameters (:class:`~risp_tasks.tasks.simulate.InitialState`);
actions from ``--actions``.
"""

from __future__ import annotations

import time

import torch

from risp_data.errors import RispError

from .context import Context
from .loop import Problem, make_loss
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


#: Grid of ``--init scan`` per identified parameter: x = 0, 1/16, …, 1 (the rod's log10 E in steps of 0.1875).
SCAN_POINTS = 17


def scan_start(loss, states_at, m: int, points: int = SCAN_POINTS, progress: bool = False
               ) -> tuple[torch.Tensor, dict]:
    """``--init scan``: the start x₀ ∈ [0, 1]^m of the local descent, from the loss evaluated on a grid.

    One parameter (quadrotor, cube, rod): x₀ = argmin over x ∈ {0, 1/(G−1), …, 1} of L(s(x)).  Several (the
    hand's five stiffnesses): one pass of coordinate search from x = ½ — coordinate j in turn takes the grid value that
    minimises L with the others held at their current values (the fingers move nearly independently, so the
    loss is close to a sum of one-parameter terms).  Ties go to the grid point nearest the current value (a loss
    that does not see a parameter leaves it at ½ instead of moving it to the range's end).  G·m rollouts without
    gradients; a grid point whose loss is NaN or whose rollout the simulator refuses (RispError, e.g. the rod's
    Newton solve) counts as +∞, never the start.  ``loss(states) -> scalar``; ``states_at(x) -> (n_source, S)``
    the simulated states with parameters x.  Returns x₀ and what was scanned (the grid, the loss at every grid
    point per coordinate)."""
    from tqdm import tqdm

    grid = torch.linspace(0.0, 1.0, points, dtype=torch.float64)
    x = torch.full((m,), 0.5, dtype=torch.float64)
    scanned = []
    bar = tqdm(total=points * m, desc="scanning the start", unit="rollout", disable=not progress, leave=False)
    with torch.no_grad(), bar:
        for j in range(m):
            values = []
            for g in grid:
                bar.update()
                trial = x.clone()
                trial[j] = g
                try:
                    value = float(loss(states_at(trial)))
                except RispError:  # a parameter the simulator cannot roll out (e.g. the rod's Newton solve)
                    value = float("nan")
                values.append(value if value == value else float("inf"))  # a NaN rollout is never the start
            best = min(range(points), key=lambda i: (values[i], abs(float(grid[i] - x[j]))))
            if values[best] == float("inf"):
                raise RispError("--init scan: the loss is not finite anywhere on the scanned grid (check --actions "
                                "and the video)")
            x[j] = grid[best]
            scanned.append(values)
    return x, {"grid_x": grid.tolist(), "loss": scanned}


def build(ctx: Context) -> Problem:
    sim, names = ctx.sim, IDENTIFIED[ctx.sim.env]
    if ctx.cfg.init == "random":
        x0 = torch.from_numpy(ctx.rng.random(len(names)))
    elif ctx.cfg.init in ("default", "scan"):
        x0 = torch.full((len(names),), 0.5, dtype=torch.float64)
    else:
        raise RispError("sysid takes --init default, random or scan")
    free = FreeParameters(sim, sim.default_params(), x0)
    if sim.action_dim and ctx.file_actions is None:
        raise RispError(f"sysid of the {sim.env} needs its commands: pass --actions A.csv")
    file_actions = None if ctx.file_actions is None else torch.from_numpy(ctx.file_actions)
    s0 = InitialState(ctx, fit=ctx.cfg.fit_initial_state)

    def states():
        p = free()
        actions = None if file_actions is None else to_sim_actions(sim, p, file_actions)
        return frame_states(sim, p, s0(), actions, ctx.n_source, ctx.k)

    info = s0.info()
    if ctx.cfg.init == "scan":  # the state loss (N's readings of the video) whatever --loss: rollouts only
        loss = make_loss("state", ctx.env, ctx.keep, ctx.predicted_targets, None, None, residual=ctx.cfg.residual)

        def states_at(x):
            with torch.no_grad():
                free.x.copy_(x)
            return states()

        started = time.perf_counter()
        x0, scanned = scan_start(loss, states_at, len(names), progress=ctx.cfg.progress)
        scanned["seconds"] = time.perf_counter() - started
        free.x0 = x0
        with torch.no_grad():
            free.x.copy_(x0)
        info = {**info, "init_scan": {"parameters": list(names), "points": SCAN_POINTS, **scanned,
                                      "grid": [[float(lo + (hi - lo) * g) for g in scanned["grid_x"]]
                                               for lo, hi in (parameter_ranges(sim)[n] for n in names)]}}
    return Problem(variables={"x": free.x, **s0.variables}, states=states,
                   estimates=lambda: {**free.estimates(), **s0.info()}, project=free.project, info=info)
