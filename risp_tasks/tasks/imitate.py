"""``risp-task imitate``: the action sequence that reproduces a video's motion (paper Sec. 5.4/5.5).

Actions are one row per source frame (held over the frame's k simulator steps), or K knots of a piecewise-linear
command per action (``--action-knots``; on the hand the default chooses K by cross-validation over the video's
frames, ``knots_setting``), optimised in normalised
coordinates u = centre + scale·x (centre: hover for the quadrotor, 0 otherwise; scale: ACTION_SCALE).
Initialisation (``--init``): ``default`` x = 0; ``random`` x ~ U(−1, 1) (seeded); ``track`` (quadrotor) a
geometric tracking controller (Lee et al. 2010) flown in the simulator along the network-estimated
trajectory; the refinement then adjusts the controller's reference path, and the actions are the commands
the controller issues (paper Sec. 5.5: long horizons are chaotic in open loop).  Physical parameters are the
simulator's nominal ones, or those ``--params`` gives; with ``--fit-params`` (by default on the hand and the rod:
:func:`fits_params`) sysid's parameters are identified jointly with the actions
(:class:`~risp_tasks.tasks.sysid.FreeParameters`).  The initial state comes from the
first two frames' estimates (``--fit-initial-state``: optimised jointly with the actions,
:class:`~risp_tasks.tasks.simulate.InitialState`).
"""

from __future__ import annotations

import copy
import dataclasses
import time

import torch

from risp_data.errors import RispError

from .config import AUTO_KNOTS, AUTO_KNOTS_LOSSES
from .context import Context
from .loop import Problem, Timer, make_loss, optimize
from .simulate import (ACTION_SCALE, InitialState, action_centre, frame_states, read_params, to_file_actions,
                       with_params)


TRACK_SCALE = 0.1  # m: the normalised reference-path offsets of ``--init track``


def initial_actions(ctx: Context, params: torch.Tensor, n_frames: int) -> torch.Tensor:
    """x0 (n_frames, A) in normalised coordinates (``default``, ``random``)."""
    if ctx.cfg.init == "random":
        return torch.from_numpy(ctx.rng.uniform(-1, 1, (n_frames, ctx.sim.action_dim)))
    return torch.zeros(n_frames, ctx.sim.action_dim, dtype=torch.float64)


def knot_basis(n_frames: int, knots: int) -> torch.Tensor:
    """W (n_frames, K): the hat functions of K knots evenly spaced over the frames, t_j = j·(n − 1)/(K − 1), so
    that actions = W @ z interpolates the knot values z (K, A) linearly (K = 0 or K = n: the identity, one row per
    frame; the tasks refuse K > n, build).  Rows sum to 1; W has full column rank for 2 ≤ K ≤ n."""
    if knots == 0 or knots >= n_frames:
        return torch.eye(n_frames, dtype=torch.float64)
    t = torch.arange(n_frames, dtype=torch.float64) * (knots - 1) / max(n_frames - 1, 1)  # frame → knot coordinate
    return torch.clamp(1 - (t[:, None] - torch.arange(knots, dtype=torch.float64)[None, :]).abs(), min=0)


#: --action-knots auto: the candidates K = round(f·n) for these fractions f of the n action rows, and n itself (one
#: row per frame, the paper's parametrisation), each K >= 2
KNOT_FRACTIONS: tuple[float, ...] = (0.25, 0.4, 0.6)
#: the frames held out in turn: every other compared frame after the first two (which the initial state is read from)
KNOT_FOLDS = 2


def knot_candidates(n_frames: int) -> list[int]:
    """The K that ``--action-knots auto`` compares (ascending; n_frames = one row per frame)."""
    return sorted({max(2, min(n_frames, round(f * n_frames))) for f in KNOT_FRACTIONS} | {n_frames})


def choose_knots(ctx: Context, n_frames: int) -> tuple[int, dict]:
    """``--action-knots auto``: K by two-fold cross-validation over the compared frames (docs/tasks.md §Smooth
    commands).  The compared frames after the first two are split into two folds, alternate frames; for each
    candidate K (:func:`knot_candidates`) and fold f the commands are fitted to N's readings of every compared frame
    but fold f's — the task's own optimiser, iterations, start and residual, always with the ``state`` loss — and
    scored by the same residual on fold f's readings.  CV(K) = Σ_f Σ_{t∈f} ρ(τ(s_t) − N(I_t)) / Σ_f |f| (ρ: the
    squared or absolute norm of ``--residual``); the smallest CV(K) wins, ties the fewer knots.

    Why: one row per frame lets the commands follow the readings' frame-to-frame error, few knots cannot follow fast
    commands; which is worse depends on the video (its commands and how well N reads it), and the held-out frames'
    readings measure it without ground truth.  Returns (K, the record result.json keeps); K = 0 when the video has too
    few frames to hold any out."""
    cfg, keep = ctx.cfg, ctx.keep
    positions = list(range(2, len(keep)))
    if len(positions) < 2 * KNOT_FOLDS:
        return 0, {"chosen": 0, "reason": f"{len(keep)} compared frames: too few to hold out every other one after "
                                          f"the first two (needs {2 + 2 * KNOT_FOLDS}); one row per frame"}
    from tqdm import tqdm

    started = time.perf_counter()
    candidates = knot_candidates(n_frames)
    folds = [positions[f::KNOT_FOLDS] for f in range(KNOT_FOLDS)]
    targets = ctx.predicted_targets

    def frames_loss(pos):
        return make_loss("state", ctx.env, [keep[p] for p in pos], targets[pos], None, None, residual=cfg.residual)

    scores = []
    bar = tqdm(total=len(candidates) * KNOT_FOLDS, desc="choosing knots", unit="fit", disable=not cfg.progress,
               leave=False)
    for K in candidates:
        held_sum = 0.0
        for fold in folds:
            trial_cfg = dataclasses.replace(cfg, action_knots=0 if K >= n_frames else K)
            # the same random start as the final fit: a copy of the task's generator, not a draw from it
            trial = build(dataclasses.replace(ctx, cfg=trial_cfg, rng=copy.deepcopy(ctx.rng)), n_frames)
            train = [p for p in range(len(keep)) if p not in fold]
            optimize(trial, frames_loss(train), optimizer=cfg.optimizer, lr=cfg.lr, momentum=cfg.momentum,
                     iterations=cfg.iterations, timer=Timer(), progress=False)
            with torch.no_grad():
                held_sum += float(frames_loss(fold)(trial.states())) * len(fold)
            bar.update()
        scores.append(held_sum / len(positions))
    bar.close()
    best = min(range(len(candidates)), key=lambda i: (scores[i], candidates[i]))
    chosen = candidates[best]
    return (0 if chosen >= n_frames else chosen), {
        "candidates": candidates, "held_out_loss": scores, "chosen": chosen, "folds": KNOT_FOLDS,
        "loss": "state", "residual": cfg.residual, "seconds": time.perf_counter() - started}


def estimated_path(ctx: Context, n_frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference positions and velocities (n_frames, 3) of the tracking controller: the network-estimated
    positions, linearly interpolated between kept frames, velocities by central differences."""
    import numpy as np

    t_keep = np.asarray(ctx.keep, np.float64)
    pos = ctx.predicted[:, :3].detach().numpy()
    t = np.arange(n_frames, dtype=np.float64)
    ref_p = np.stack([np.interp(t, t_keep, pos[:, i]) for i in range(3)], 1)
    return torch.tensor(ref_p), torch.tensor(np.gradient(ref_p, axis=0) * ctx.fps)


def tracked_rollout(ctx: Context, params: torch.Tensor, s0: torch.Tensor, ref_p: torch.Tensor, ref_v: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed loop: a geometric tracking controller (Lee et al. 2010) flies the simulator along ref_p, one command
    per frame.  Returns (environment states (n, S), commands (n, 4)); differentiable w.r.t. ref_p."""
    from risp_data.envs.quadrotor import ARM_LENGTH

    from ..sims.quadrotor_control import tracking_thrusts

    sim = ctx.sim
    mass = float(params[0, sim.param_index("mass")])
    inertia = params[0, [sim.param_index(n) for n in ("Ixx", "Iyy", "Izz")]]
    k_m, k_f = float(params[0, sim.param_index("k_m")]), float(params[0, sim.param_index("k_f")])
    s, states, commands = s0, [s0], []
    for i in range(len(ref_p)):
        u = tracking_thrusts(s, ref_p[i:i + 1], ref_v[i:i + 1], mass, inertia, k_m, ARM_LENGTH) / k_f
        commands.append(u[0])
        if i == len(ref_p) - 1:
            break
        for j in range(ctx.k):
            s = sim.step(params, s, u, i * ctx.k + j)
        states.append(s)
    return sim.to_env_state(torch.cat(states)), torch.stack(commands)


def _track_problem(ctx: Context, params: torch.Tensor, s0, n_frames: int, given: dict[str, float]) -> Problem:
    """``--init track``: the tracking controller's reference path is what is refined (offsets δ_t = 0.1 m · x_t
    added to the estimated path); the controller keeps the long open-loop horizon stable, and the actions are
    the commands it issues.  (Refining raw commands over 14 s diverged in one step: the open loop is chaotic.)"""
    if ctx.sim.env != "quadrotor":
        raise RispError("--init track is for the quadrotor (a tracking controller)")
    ref_p, ref_v = estimated_path(ctx, n_frames)
    x = torch.zeros(n_frames, 3, dtype=torch.float64, requires_grad=True)

    def run():
        return tracked_rollout(ctx, params, s0(), ref_p + TRACK_SCALE * x, ref_v)

    with torch.no_grad():
        initial = to_file_actions(ctx.sim, params, run()[1])

    def estimates():
        with torch.no_grad():
            commands = run()[1]
        return {"actions": to_file_actions(ctx.sim, params, commands).tolist(), "initial_actions": initial.tolist(),
                "path_offsets_m": (TRACK_SCALE * x.detach()).tolist()}

    info = {**s0.info(), "parametrisation": "tracking-controller reference path",
            **_parameter_info(ctx.sim, params, given)}
    return Problem(variables={"path_offsets": x, **s0.variables}, states=lambda: run()[0],
                   estimates=lambda: {**estimates(), **s0.info()}, info=info)


def _parameter_info(sim, params: torch.Tensor, given: dict[str, float]) -> dict:
    """result.json's record of the physical parameters simulated with (``params``: the start's, free ones at their
    start values) and of those ``--params`` set (printed by the CLI, so a user sees which values were used)."""
    return {"parameters": {n: float(params[0, i]) for i, n in enumerate(sim.param_names)},
            **({"given_parameters": dict(given)} if given else {})}


def build(ctx: Context, n_frames: int | None = None, s0: torch.Tensor | None = None) -> Problem:
    sim = ctx.sim
    # a system without actions (the cube) never gets here: run_task refuses it, naming how the model was chosen
    n_frames = ctx.n_source if n_frames is None else n_frames
    selection = None
    ctx = dataclasses.replace(ctx, cfg=dataclasses.replace(ctx.cfg, action_knots=knots_setting(ctx.cfg, sim.env)))
    if ctx.cfg.action_knots == AUTO_KNOTS:  # resolved here, so that every caller of build gets the chosen K
        knots, selection = choose_knots(ctx, n_frames)
        ctx = dataclasses.replace(ctx, cfg=dataclasses.replace(ctx.cfg, action_knots=knots))
    given = read_params(sim, ctx.cfg.params) if ctx.cfg.params else {}  # known or identified ones, read once
    params = with_params(sim, sim.default_params(), given)
    s0 = InitialState(ctx, fit=ctx.cfg.fit_initial_state, given=s0)  # control passes its given state
    if ctx.cfg.init == "track":
        if ctx.cfg.action_knots:
            raise RispError("--action-knots parametrises the commands themselves; with --init track the controller's "
                            "reference path is optimised instead (leave one of them out)")
        return _track_problem(ctx, params, s0, n_frames, given)
    centre, scale = action_centre(sim, params), ACTION_SCALE[sim.env]
    x0 = initial_actions(ctx, params, n_frames)
    free = _free_parameters(ctx, params, given) if fits_params(ctx.cfg, sim.env) else None
    physics = free if free is not None else (lambda: params)
    with torch.no_grad():
        start = physics()  # the parameters the optimisation starts from (free ones at their start values)
    if ctx.cfg.action_knots > n_frames:  # knot_basis would fall back to one row per frame, with result.json saying K
        raise RispError(f"--action-knots {ctx.cfg.action_knots} is more than the {n_frames} action rows (one per "
                        f"frame{' of the horizon and the start' if ctx.cfg.task == 'control' else ' of ' + ctx.cfg.video}"
                        f"): give at most {n_frames}, or 0 for one row per frame")
    W = knot_basis(n_frames, ctx.cfg.action_knots)
    knots = W.shape[1] < n_frames
    # with knots: the per-frame start (the same random draw as without), projected onto them by least squares
    z0 = torch.linalg.lstsq(W, x0).solution if knots else x0
    z = z0.clone().requires_grad_(True)

    def actions(v):
        return centre + scale * (W @ v if knots else v)

    def estimates():
        with torch.no_grad():
            p = physics()
        found = {"actions": to_file_actions(sim, p, actions(z.detach())).tolist(),
                 "initial_actions": to_file_actions(sim, start, actions(z0)).tolist()}
        return {**found, **(free.estimates() if free is not None else {})}

    info = {**s0.info(), "parametrisation": f"{W.shape[1]} knots, piecewise linear" if knots else "one row per frame",
            **_parameter_info(sim, start, given)}
    if free is not None:
        info["fitted_parameters"] = list(free.names)
    if selection is not None:
        info["knot_selection"] = selection
    return Problem(variables={"actions": z, **({"x": free.x} if free is not None else {}), **s0.variables},
                   states=lambda: frame_states(sim, physics(), s0(), actions(z), n_frames, ctx.k),
                   estimates=lambda: {**estimates(), **s0.info()}, info=info,
                   project=free.project if free is not None else (lambda: None))


# Where imitate chooses its command knots by cross-validation unless told otherwise (--action-knots unset), with the
# state or render loss: the environments where the rule fixed before the measurement held — `auto` at least as close
# to the truth as one row per frame on a fresh set of videos (docs/RESULTS.md §Knots chosen by cross-validation: the
# hand's twelve fresh videos 3.83× against 3.56× the random actions' error, closer on all twelve).  Not the quadrotor
# or the rod, where it was not measured; it costs 2·|candidates| + 1 fits.
AUTO_KNOTS_BY_DEFAULT: tuple[str, ...] = ("hand",)


def knots_setting(cfg, env_name: str) -> int | str:
    """``--action-knots`` as given; unset (None): ``auto`` for imitate on AUTO_KNOTS_BY_DEFAULT with the ``state`` or
    ``render`` loss and no ``--init track`` (the settings ``auto`` takes), else 0 (one row per frame)."""
    if cfg.action_knots is not None:
        return cfg.action_knots
    takes_auto = cfg.task == "imitate" and cfg.init != "track" and cfg.loss in AUTO_KNOTS_LOSSES
    return AUTO_KNOTS if takes_auto and env_name in AUTO_KNOTS_BY_DEFAULT else 0


# Where imitate identifies sysid's parameters with the commands unless told otherwise (--fit-params unset): the
# environments whose parameters shape the motion whatever the commands, and where doing so was measured to bring
# the imitation closer to the truth on every video (docs/RESULTS.md §Imitation with unknown stiffnesses): the
# rod's E sets its bending under any force (0.0065 m against 0.0256 m with the nominal E), the hand's stiffnesses
# let its commands follow the readings (11 % closer).  Not the quadrotor: with free thrusts its translation sees
# only f/m, the mass runs to a bound and the imitation got worse.
FIT_PARAMS_BY_DEFAULT: tuple[str, ...] = ("hand", "rod")


def fits_params(cfg, env_name: str) -> bool:
    """Whether imitate identifies the physical parameters: ``--fit-params``/``--no-fit-params`` when given; else
    yes for FIT_PARAMS_BY_DEFAULT unless ``--params`` gives them or ``--init track`` optimises a reference path."""
    if cfg.fit_params is not None:
        return cfg.fit_params
    return cfg.task == "imitate" and cfg.init != "track" and not cfg.params and env_name in FIT_PARAMS_BY_DEFAULT


def _free_parameters(ctx: Context, params: torch.Tensor, given: dict[str, float]):
    """``--fit-params``: sysid's identified parameters as variables (sysid.FreeParameters).  Each starts from
    the value ``--params`` gives it (clamped into its range), else from the middle of its range: the nominal
    value is no better a guess for an unknown system (the hand's nominal stiffness 1.0 is its range's edge)."""
    from .sysid import FreeParameters, parameter_ranges

    x0 = torch.tensor([min(max((given[n] - lo) / (hi - lo), 0.0), 1.0) if n in given else 0.5
                       for n, (lo, hi) in parameter_ranges(ctx.sim).items()], dtype=torch.float64)
    return FreeParameters(ctx.sim, params, x0)

