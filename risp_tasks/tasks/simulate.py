"""The simulation timeline of a task: video frames at ``fps``, k = round(1 / (fps · dt)) simulator steps per
frame, actions held constant over a frame (one action row per source frame)."""

from __future__ import annotations

import json
import math
import os

import torch

from risp_data.errors import RispError

#: Normalised action coordinates: u = centre + scale · x.  RMSProp moves x by about lr per iteration, so
#: x must be O(1) across the useful command range (quadrotor: commands around hover, u_h ≈ 147).
ACTION_SCALE = {"quadrotor": 60.0, "hand": 0.5, "rod": 40.0}


def steps_per_frame(sim, fps: float) -> int:
    """k whole simulator steps per frame, 1/fps within the sims' STEP_TOLERANCE (33.3 fps against 3 steps of 10 ms
    is 0.1 % off; a 2 % slack let 7, 9.8, 11 and 14 fps through, whose simulated time then drifted from the video's
    by 1–2 %, biasing velocities and the identified stiffness, without a word)."""
    from ..sims import step_rates, whole_steps

    k = whole_steps(sim, 1.0 / fps)
    if k is None:
        raise RispError(f"{fps:g} frames per second do not fit the {sim.env} simulator's fixed step of {sim.dt:g} s "
                        f"(1/fps must be a multiple of it: {step_rates(sim)}, … fps); a video at another rate can be "
                        f"resampled with --fps, one whose file states a rate slightly off (24.9 for 25) given its own "
                        f"with --source-fps")
    return k


def timeline(env: str, fps: float, effects: tuple[str, ...] = ()):
    """(simulator, k): k = round(1 / (fps · dt_native)) steps per frame with the step set to 1 / (fps · k), as
    diagnose does for measured data (docs/diagnose.md §Time step); simulators without a ``dt`` option keep
    their step and need 1/fps to be a multiple of it."""
    from ..sims import get_simulator

    sim = get_simulator(env, effects)
    if not fps > 0:
        raise RispError(f"the frame rate must be positive, got {fps!r}")
    k = max(1, int(round(1.0 / (fps * sim.dt))))
    dt = 1.0 / (fps * k)
    if abs(dt - sim.dt) > 1e-9 * sim.dt:
        try:
            sim = get_simulator(env, effects, dt=dt)
        except RispError:
            pass  # keep the native step; steps_per_frame explains the mismatch
    return sim, steps_per_frame(sim, fps)


def action_centre(sim, params: torch.Tensor) -> torch.Tensor:
    """Centre of the normalised actions (A,): hover for the quadrotor, zero otherwise."""
    if sim.env == "quadrotor":
        from ..sims.quadrotor import hover_command

        mass, k_f = params[0, sim.param_index("mass")], params[0, sim.param_index("k_f")]
        return hover_command(mass, k_f).expand(sim.action_dim).clone()
    return torch.zeros(sim.action_dim, dtype=params.dtype)


def set_params(sim, params: torch.Tensor, given: str, option: str = "--params") -> torch.Tensor:
    """A copy of ``params`` (1, P) with the values that ``given`` names (:func:`read_params`)."""
    return with_params(sim, params, read_params(sim, given, option))


def with_params(sim, params: torch.Tensor, values: dict[str, float]) -> torch.Tensor:
    """A copy of ``params`` (1, P) with ``values`` ({name: value}, already checked) in their places."""
    p = params.clone()
    for name, value in values.items():
        p[0, sim.param_index(name)] = value
    return p


def read_params(sim, given: str, option: str = "--params") -> dict[str, float]:
    """The parameter values that ``given`` names: a JSON object {name: value}, the path of such a JSON file, or
    the path of a task's result.json (its identified ``estimates.parameters``, e.g. a ``sysid`` run).  Unknown
    names, non-numbers and non-finite values are one error line each.  A task's result folder (what sysid prints
    after ``results:``) stands for its result.json."""
    if os.path.isdir(given):
        if not os.path.isfile(os.path.join(given, "result.json")):
            raise RispError(f"{option} {given}: a folder without a result.json; give a sysid run's result folder or "
                            "result.json, a JSON file, or a JSON object")
        given = os.path.join(given, "result.json")
    if os.path.isfile(given):
        from .inputs import read_json

        data = read_json(given, option.lstrip("-"))  # a JSON object, or one line naming the file
        if isinstance(data, dict) and "task" in data:  # a task's result.json: its identified parameters
            estimates = data.get("estimates")
            found = estimates.get("parameters") if isinstance(estimates, dict) else None
            if not isinstance(found, dict):
                raise RispError(f"{given}: {option}: this {data['task']!s:.20} result holds no identified parameters "
                                f"(estimates.parameters); give a sysid (or imitate --fit-params) run's result.json")
            data = found
        at = f"{given}: "
    else:
        try:
            data = json.loads(given)
        except ValueError:
            looks_like_json = given.lstrip().startswith(("{", "["))
            if not looks_like_json and (given.endswith(".json") or os.sep in given):  # a path: say it is not there
                raise RispError(f"{option} {given}: no such file or folder (give a JSON object, a JSON file or a "
                                "sysid result folder)") from None
            raise RispError(f"{option} must be a JSON object of parameter values or a JSON file, got {given[:60]!r}") from None
        at = ""
    if not isinstance(data, dict):
        raise RispError(f"{at}{option} must be a JSON object of parameter values, got {str(data)[:40]!r}")
    values = {}
    for name, value in data.items():
        if name not in sim.param_names:
            raise RispError(f"{at}{option}: unknown {sim.env} parameter {name!r}; known: {', '.join(sim.param_names)}")
        try:  # bool is an int in Python: rejected with the strings and lists; float() overflows on huge ints
            ok = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(float(value))
        except OverflowError:
            ok = False
        if not ok:
            raise RispError(f"{at}{option}: {name!r} must be a finite number, got {str(value)[:40]!r}")
        values[name] = float(value)
    # a negative mass: one line naming the option (the defaults around the given values are within bounds)
    sim.check_param_bounds(with_params(sim, sim.default_params(), values), f"{at}{option}: ")
    return values


def to_sim_actions(sim, params: torch.Tensor, file_actions: torch.Tensor) -> torch.Tensor:
    """Actions file units (quadrotor thrusts [N]) -> simulator commands (quadrotor u = f / k_f)."""
    if sim.env == "quadrotor":
        return file_actions / params[0, sim.param_index("k_f")]
    return file_actions


def to_file_actions(sim, params: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    if sim.env == "quadrotor":
        return actions * params[0, sim.param_index("k_f")]
    return actions


def initial_sim_state(sim, first: torch.Tensor, second: torch.Tensor | None, fps: float) -> torch.Tensor:
    """A full simulator state (1, X) from the environment states of the first two frames: pose from the first,
    linear velocity from their difference (rigid bodies), joint rates likewise (hand); the rod starts from its
    rest state (its videos start at rest)."""
    dtype = torch.float64
    first = first.to(dtype)
    if sim.env in ("quadrotor", "cube"):
        from risp_data.envs.rotations import euler_to_quat

        s = torch.zeros(1, len(sim.state_names), dtype=dtype)
        s[0, :3] = first[:3]
        s[0, 3:7] = euler_to_quat(first[3], first[4], first[5])
        if second is not None:
            s[0, 7:10] = (second.to(dtype)[:3] - first[:3]) * fps
        if len(sim.state_names) > 13:  # motor-lag thrust states start at hover
            s[0, 13:17] = sim.default_params()[0, sim.param_index("mass")] * 9.81 / 4
        return s
    if sim.env == "hand":
        s = sim.default_state(1, dtype)
        n = first.shape[-1]
        s[0, :n] = first
        if second is not None:
            s[0, n:2 * n] = (second.to(dtype) - first) * fps
        return s
    return sim.default_state(1, dtype)


#: Step scales of a fitted initial state (``--fit-initial-state``) per unit of its normalised offsets x.
#: RMSProp moves x by about lr per iteration, so the paper's 100 steps at lr 3e-3 reach about ±0.3–0.6 scale:
#: a few centimetres, up to ~15°, ~0.5 rad/s — the size of the network's per-frame errors.
INITIAL_STEP = {"position": 0.1, "angle": 0.5, "angular_velocity": 1.0}  # m, rad, rad/s per unit of x


class InitialState:
    """The simulator's initial state s₀ of a task, from the network's estimates ŝ₀, ŝ₁ of the first two kept frames
    (:func:`initial_sim_state`: pose from ŝ₀, velocities from ŝ₁ − ŝ₀).  Fixed by default for ``fit=False``;
    when fitted, offsets x (2, S) are optimised jointly with the task's own variables:

        s₀(x) = initial_sim_state(ŝ₀ + σ ⊙ x₀, ŝ₁ + σ ⊙ x₁)            (hand: joint angles and rates)
        quadrotor, cube: as above for position, attitude and linear velocity (x₁'s positions), and the body
        angular velocity ω₀ = σ_ω · x₁[yaw, pitch, roll] (from 0: differencing two noisy attitudes at 10 fps
        would give rad/s of noise)

    with σ from :data:`INITIAL_STEP`, so that N's errors on the first frames are corrected by the whole video
    instead of being carried through the rollout.  ``fit=None`` (the default): fitted where s₀ is read from the
    video (quadrotor, cube, hand; the rod's videos start at rest).  ``given``: a full simulator state used as it
    is (control's ``--initial-state``), never fitted."""

    def __init__(self, ctx, fit: bool | None = None, given: torch.Tensor | None = None):
        sim = ctx.sim
        if given is not None:  # control's --initial-state: a given full simulator state, fixed
            fit = False
        elif fit is None:
            fit = sim.env != "rod"
        self.sim, self.fit = sim, fit
        self.first = ctx.predicted[0].double()
        self.second = ctx.predicted[1].double() if len(ctx.keep) > 1 else None
        self.fps = ctx.fps / (ctx.keep[1] - ctx.keep[0]) if len(ctx.keep) > 1 else ctx.fps
        self.variables: dict[str, torch.Tensor] = {}
        # not fitted: one s₀ for the whole run, made once (not once per iteration)
        self.fixed = None if fit else (given if given is not None else
                                       initial_sim_state(sim, self.first, self.second, self.fps))
        if fit:
            if sim.env == "rod":
                raise RispError("--fit-initial-state: the rod's videos start at rest; its initial state is not "
                                "read from the video (use --fixed-initial-state)")
            names = ctx.env.state_names
            self.step = torch.tensor([INITIAL_STEP["position" if n in ("x", "y", "z") else "angle"] for n in names],
                                     dtype=torch.float64)
            self.x = torch.zeros(2, len(names), dtype=torch.float64, requires_grad=True)
            self.variables = {"initial_state": self.x}

    @property
    def rigid(self) -> bool:
        return self.sim.env in ("quadrotor", "cube")

    def __call__(self) -> torch.Tensor:
        """s₀ (1, X), differentiable w.r.t. the offsets when fitted."""
        if not self.fit:
            return self.fixed
        first = self.first + self.step * self.x[0]
        if self.rigid:
            second = None if self.second is None else torch.cat([self.second[:3] + self.step[:3] * self.x[1, :3],
                                                                   first[3:]])
            s0 = initial_sim_state(self.sim, first, second, self.fps)
            omega = INITIAL_STEP["angular_velocity"] * self.x[1, 3:6]
            return torch.cat([s0[:, :10], omega[None], s0[:, 13:]], 1)
        second = None if self.second is None else self.second + self.step * self.x[1]
        return initial_sim_state(self.sim, first, second, self.fps)

    def info(self) -> dict:
        with torch.no_grad():
            out = {"initial_state": self().detach()[0].tolist(), "initial_state_fitted": self.fit}
            if self.fit:  # σ ⊙ x as s₀ uses it: the rigid bodies' second-row angle entries are ω₀ = σ_ω · x
                offsets = self.step * self.x.detach()
                if self.rigid:
                    offsets[1, 3:6] = INITIAL_STEP["angular_velocity"] * self.x.detach()[1, 3:6]
                out["initial_state_offsets"] = offsets.tolist()
        return out


def frame_states(sim, params: torch.Tensor, s0: torch.Tensor, actions: torch.Tensor | None, n_frames: int,
                 k: int) -> torch.Tensor:
    """Environment states (n_frames, S) at the video frames; ``actions`` (n_frames, A) per frame in simulator
    units (held for the k steps after each frame) or None."""
    steps = (n_frames - 1) * k
    per_step = None
    if actions is not None:
        per_step = actions.repeat_interleave(k, 0)[None, :max(steps, 1)]
    states = sim.rollout(params, s0, per_step, steps)[0, ::k]
    return sim.to_env_state(states)


def wrap_angles(delta: torch.Tensor, angular: list[bool]) -> torch.Tensor:
    """Δ with the angular components wrapped to [−π, π) (|Δ| is what the errors use: ±π alike)."""
    mask = torch.tensor(angular, dtype=torch.bool)
    wrapped = torch.remainder(delta + math.pi, 2 * math.pi) - math.pi
    return torch.where(mask, wrapped, delta)
