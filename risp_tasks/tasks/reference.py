"""Reference videos with ground truth (``risp-task make-video``; docs/tasks.md §Reference videos).

Simulate an environment with chosen or random parameters, initial state and actions, render every frame in
the ``target`` domain with one random look (risp_data.psi.sample_rendering) by the domain's reference
integrator, and write the video, ``<stem>.truth.json`` (states, parameters, actions, look, seed — read by no
solver) and, for actuated systems, ``<stem>.actions.csv`` (the known commands, one row per frame).

Motions: quadrotor — a geometric tracking controller with an integral term follows a random smooth path inside the sampled flight
volume (its per-frame thrusts are the actions); cube — a toss (random pose, velocity and spin); hand — random
smooth finger torques; rod — a sinusoidal vertical force on its centre.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass

import numpy as np
import torch

from risp_data.atomic import check_writable, write_text_atomic
from risp_data.errors import RispError
from risp_data.threads import set_drjit_threads, set_torch_threads


# The reference flights' controller: tracking_thrusts' PD law plus its integral term KI·∫e_p dt, as real flight
# controllers have: a steady disturbance (a hidden wind) is compensated by the commands instead of pushing the
# vehicle out of the sampled flight volume (s³ + KD·s² + KP·s + KI is stable for KI < KD·KP = 12).
KI = 2.0

# The reference tosses (cube): the end of the horizontal slide is aimed this far inside the sampled x, y range,
# and each horizontal velocity component is at most TOSS_SPEED (the tosses' former range, ±0.8 m/s).
TOSS_MARGIN = 0.02  # m
TOSS_SPEED = 0.8  # m/s

# Revisions of a motion: a table's cached reference video is keyed by its environment's revision as well as its
# settings and look (risp_tasks.tables.artifacts), so a video made by an older motion is not found again.
# cube 2: tosses aimed inside the sampled x, y range (before: up to ±0.8 m/s in any direction, 2026-11-27).
MOTION_REVISIONS = {"cube": 2}

# outside_sampled_states: how far beyond the sampled box, as a share of each state's range, still counts as inside
OUTSIDE_TOLERANCE = 0.01


@dataclass(frozen=True)
class ReferenceConfig:
    env: str
    out: str
    frames: int = 20
    fps: float = 10.0
    resolution: int = 64
    spp: int = 16
    domain: str = "target"
    params: str | None = None  # JSON object {name: value}
    effect: str | None = None  # NAME or NAME:v1,v2,...
    camera: str | None = None
    mesh: str | None = None  # vehicle mesh file (quadrotor; docs/tasks.md §Vehicle mesh)
    seed: int = 0
    progress: bool = True
    overwrite: bool = False  # replace a video, ground truth or actions file already at ``out``


def truth_path(out: str) -> str:
    return os.path.splitext(os.path.normpath(out))[0] + ".truth.json"


def actions_path(out: str) -> str:
    return os.path.splitext(os.path.normpath(out))[0] + ".actions.csv"


def _parse_effect(spec: str | None, sim_env: str):
    if not spec:
        return None, None
    name, _, values = spec.partition(":")
    vals = None
    if values:
        try:
            vals = [float(v) for v in values.split(",")]
        except ValueError:
            raise RispError(f"--effect {spec!r}: values must be numbers, e.g. wind:3,0,0") from None
        if not all(math.isfinite(v) for v in vals):  # float() reads "nan" and "inf"
            raise RispError(f"--effect {spec!r}: values must be finite numbers, e.g. wind:3,0,0")
    return name.strip(), vals


def _params(cfg: ReferenceConfig, sim, rng, effect, effect_values) -> torch.Tensor:
    from .sysid import parameter_ranges

    p = sim.default_params()
    for name, (lo, hi) in parameter_ranges(sim).items():
        p[0, sim.param_index(name)] = float(rng.uniform(lo, hi))
    if cfg.params:
        from .simulate import set_params

        p = set_params(sim, p, cfg.params, "--params")
    if effect and effect_values is not None:
        names = [n for n in sim.param_names if n.startswith(effect + ".")]
        if len(names) != len(effect_values):
            raise RispError(f"--effect {effect}: needs {len(names)} values ({', '.join(names)})")
        for n, v in zip(names, effect_values):
            p[0, sim.param_index(n)] = v
    sim.check_param_bounds(p, "--params / --effect: ")  # the flight controller would fly a negative mass
    return p


def _motion(sim, params, n, k, fps, rng):
    """(full states (n, X), file actions (n, A) or None) of the environment's reference motion: n frames at
    ``fps``, k simulation steps per frame, random numbers drawn from ``rng`` in a fixed order."""
    if sim.env == "quadrotor":
        return _flight(sim, params, n, k, fps, rng)
    if sim.env == "cube":
        return _toss(sim, params, n, k, fps, rng)
    return _driven(sim, params, n, k, fps, rng)


def _flight(sim, params, n, k, fps, rng):
    """The quadrotor follows p_ref(t) = c + a·sin(2π f t + φ) per axis (a: 0.4–0.8 of the sampled half-range, f:
    0.15–0.35 Hz) under the tracking controller with its integral term; the actions are its per-frame thrusts."""
    from risp_data.envs import get_environment
    from risp_data.envs.quadrotor import ARM_LENGTH

    from ..sims.quadrotor_control import tracking_thrusts

    env = get_environment(sim.env)
    low, high = np.asarray(env.state_low[:3]), np.asarray(env.state_high[:3])
    centre, half = (low + high) / 2, (high - low) / 2
    t = np.arange(n) / fps
    amp = half * rng.uniform(0.4, 0.8, 3)
    freq = rng.uniform(0.15, 0.35, 3)
    phase = rng.uniform(0, 2 * math.pi, 3)
    ref_p = torch.tensor(centre + amp * np.sin(2 * math.pi * freq * t[:, None] + phase))
    ref_v = torch.tensor(amp * 2 * math.pi * freq * np.cos(2 * math.pi * freq * t[:, None] + phase))
    s = torch.zeros(1, len(sim.state_names), dtype=torch.float64)
    s[0, :3], s[0, 3], s[0, 7:10] = ref_p[0], 1.0, ref_v[0]
    mass = float(params[0, sim.param_index("mass")])
    inertia = params[0, [sim.param_index(n_) for n_ in ("Ixx", "Iyy", "Izz")]]
    k_m, k_f = float(params[0, sim.param_index("k_m")]), float(params[0, sim.param_index("k_f")])
    states, thrusts = [s], []
    integral = torch.zeros(1, 3, dtype=torch.float64)  # ∫ (p_ref − p) dt: the flight controller's I term
    with torch.no_grad():
        for i in range(n):
            integral += (ref_p[i:i + 1] - s[:, :3]) / fps
            f = tracking_thrusts(s, ref_p[i:i + 1], ref_v[i:i + 1], mass, inertia, k_m, ARM_LENGTH,
                                 integral=integral, ki=KI)
            thrusts.append(f[0])
            if i == n - 1:
                break
            for j in range(k):
                s = sim.step(params, s, f / k_f, i * k + j)
            states.append(s)
    return torch.cat(states), torch.stack(thrusts).numpy()


def _toss(sim, params, n, k, fps, rng):
    """The cube starts at a random attitude (pitch within ±90°), x, y ∈ ±0.15 m, 0.2–0.35 m high, spinning at up
    to 6 rad/s about each axis, with the horizontal velocity of :func:`toss_velocity`; no actions."""
    from risp_data.envs.rotations import euler_to_quat

    s = torch.zeros(1, len(sim.state_names), dtype=torch.float64)
    ypr = rng.uniform(-math.pi, math.pi, 3) * np.array([1, 0.5, 1])
    s[0, 0:2] = torch.tensor(rng.uniform(-0.15, 0.15, 2))
    s[0, 2] = float(rng.uniform(0.2, 0.35))
    s[0, 3:7] = euler_to_quat(*torch.tensor(ypr).unbind())
    s[0, 7:9] = torch.tensor(toss_velocity(s[0, 0:2].numpy(), rng.uniform(-1, 1, 2), (n - 1) / fps))
    s[0, 10:13] = torch.tensor(rng.uniform(-6, 6, 3))
    with torch.no_grad():
        return sim.rollout(params, s, None, (n - 1) * k)[0, ::k], None


def _driven(sim, params, n, k, fps, rng):
    """Hand and rod: from the rest state, each action u_a(t) = A_a·sin(2π f_a t + φ_a), held over a frame (A: hand
    0.1–0.4 N·m per finger, rod 20–60 N on its centre; f: 0.3–1 Hz); the actions file holds u at the frames."""
    A = sim.action_dim
    t = np.arange(n) / fps
    amp = rng.uniform(*{"hand": (0.1, 0.4), "rod": (20.0, 60.0)}[sim.env], (1, A))
    u = amp * np.sin(2 * math.pi * rng.uniform(0.3, 1.0, (1, A)) * t[:, None] + rng.uniform(0, 2 * math.pi, (1, A)))
    s = sim.default_state(1, torch.float64)
    with torch.no_grad():
        per_step = torch.tensor(u).repeat_interleave(k, 0)[None, :max((n - 1) * k, 1)]
        return sim.rollout(params, s, per_step, (n - 1) * k)[0, ::k], u


def toss_velocity(xy0: np.ndarray, u: np.ndarray, duration: float) -> np.ndarray:
    """The horizontal velocity of a reference toss that ends where ``u`` ∈ [−1, 1]² points inside the sampled box.

    On the frictionless floor of the base cube model the normal contact forces are vertical, so the horizontal
    velocity is constant and the centre moves on the segment xy(t) = xy0 + v·t: aiming its end at
    xy_end = u · (XY_RANGE − TOSS_MARGIN) keeps every frame of the toss inside the sampler's x, y range, which
    the networks are trained on (docs/tasks.md §Reference videos).  Each component is capped at
    TOSS_SPEED m/s (short videos), which shortens the segment.  Friction (an effect, not used by the tasks)
    would slow the cube along it and, with spin, deflect it at impacts; a toss that leaves the box makes
    make-video warn."""
    from risp_data.envs.cube import XY_RANGE

    end = np.asarray(u, np.float64) * (XY_RANGE - TOSS_MARGIN)
    return np.clip((end - np.asarray(xy0, np.float64)) / max(duration, 1e-9), -TOSS_SPEED, TOSS_SPEED)


def outside_sampled_states(env_name: str, env_states: np.ndarray) -> dict:
    """Which frames' states lie outside the box the environment's sampler draws training states from.

    The networks are trained on states uniform in [state_low, state_high] (risp_data.envs); a reference motion
    may leave that box (a toss that slides away, a flight that overshoots its path), and there a network's
    reading is an extrapolation.  Returns {"fraction": share of frames with any state outside, "states": {name:
    share of frames outside, for the states that leave}, "low", "high"}.  A state within OUTSIDE_TOLERANCE of its
    range beyond the box counts as inside: the simulated cube resting on the floor sits up to 0.4 mm below the
    box's z (its penalty contact's penetration), which is no extrapolation."""
    from risp_data.envs import get_environment

    env = get_environment(env_name)
    lo, hi = np.asarray(env.state_low, np.float64), np.asarray(env.state_high, np.float64)
    S = np.asarray(env_states, np.float64)
    tol = OUTSIDE_TOLERANCE * (hi - lo)
    out = (S < lo - tol) | (S > hi + tol)
    return {"fraction": float(out.any(axis=1).mean()),
            "states": {n: float(out[:, i].mean()) for i, n in enumerate(env.state_names) if out[:, i].any()},
            "low": lo.tolist(), "high": hi.tolist()}


def outside_warning(outside: dict) -> str | None:
    """The one-line warning make-video prints for :func:`outside_sampled_states`, or None when all frames are in."""
    if not outside["fraction"] > 0:
        return None
    per = ", ".join(f"{n} {100 * f:.0f} %" for n, f in outside["states"].items())
    return (f"warning: {100 * outside['fraction']:.0f} % of the frames have states outside the range the networks are "
            f"trained on ({per}): a network's readings there are extrapolations (docs/tasks.md §Reference videos)")


def check_video_size(cfg: ReferenceConfig) -> None:
    """Refuse, before anything is rendered, frames Mitsuba cannot render or a video this machine cannot hold
    (the frames are kept as float32 RGB until the video is written; the renderer's film needs ≈ 3× one frame)."""
    from risp_data.generate import available_memory, check_image_size

    check_image_size(cfg.resolution, cfg.spp, cfg.domain, "--resolution")
    need = (cfg.frames + 4) * cfg.resolution * cfg.resolution * 3 * 4
    have = available_memory()
    if have is not None and need > have:
        raise RispError(f"--resolution {cfg.resolution} for {cfg.frames} frames needs about {need / 2**30:.1f} GiB of "
                        f"memory, {have / 2**30:.1f} GiB are available: lower --resolution or --frames")


def make_reference(cfg: ReferenceConfig) -> dict:
    """Simulate, render and write one reference video with its ground truth and actions (docs/tasks.md §Reference
    videos); returns the truth.  It sets its own thread counts (one torch thread, Dr.Jit on every CPU it may use,
    recorded in the truth) and gives the caller's back when it returns: the tables make videos in-process, between
    cells that run on one thread each."""
    import sys

    torch_before = torch.get_num_threads()
    drjit = sys.modules.get("drjit")  # not imported yet: nobody has set its count (importing it here comes too early)
    drjit_before = drjit.thread_count() if drjit is not None else None
    try:
        return _make_reference(cfg)
    finally:
        torch.set_num_threads(torch_before)
        if drjit_before is not None:
            drjit.set_thread_count(drjit_before)


def _make_reference(cfg: ReferenceConfig) -> dict:
    from tqdm import tqdm

    from risp_data.psi import sample_rendering
    from risp_data.render import Renderer

    from ..video import check_video_path, made_by, sha256_file, write_video
    from .inputs import read_camera, render_environment, write_actions
    from .results import versions
    from .simulate import timeline

    for bad, rule, value in ((cfg.frames < 2, "--frames must be >= 2", cfg.frames),
                             (not cfg.fps > 0, "--fps must be > 0", cfg.fps),
                             (cfg.resolution < 2, "--resolution must be >= 2", cfg.resolution),
                             (cfg.seed < 0, "--seed must be >= 0", cfg.seed),
                             (cfg.spp < 1, "--spp must be >= 1", cfg.spp)):
        if bad:
            raise RispError(f"{rule}, got {value}")
    check_video_size(cfg)
    check_video_path(cfg.out, cfg.overwrite)  # before the render: a .gif or a folder of other files fail here
    check_writable(os.path.dirname(os.path.abspath(cfg.out)), f"--out {cfg.out}: its folder")
    for side, what in ((truth_path(cfg.out), "ground truth"), (actions_path(cfg.out), "actions")):
        if os.path.lexists(side) and not os.path.isfile(side):  # written after the video: refuse now what would fail
            raise RispError(f"{side}: exists and is not a file (the video's {what} file goes there); move it away "
                            "or give another --out")
    if not cfg.overwrite:  # a video's ground truth and actions belong to it: never replace them unasked
        held = [p for p in (cfg.out, truth_path(cfg.out), actions_path(cfg.out)) if os.path.exists(p)]
        if held:
            raise RispError(f"{held[0]}: exists (a reference video's files: {', '.join(held)}); give another --out, "
                            f"or --overwrite to replace them")
    torch_threads = set_torch_threads(1)  # the simulation is small: one torch thread, as the tasks' default
    drawn = render_environment(cfg.env, cfg.mesh)
    rng = np.random.default_rng(cfg.seed)
    effect, effect_values = _parse_effect(cfg.effect, cfg.env)
    sim, k = timeline(cfg.env, cfg.fps, (effect,) if effect else ())
    params = _params(cfg, sim, rng, effect, effect_values)
    full, actions = _motion(sim, params, cfg.frames, k, cfg.fps, rng)
    env_states = sim.to_env_state(full).numpy()
    look = sample_rendering(cfg.env, cfg.domain, rng)
    renderer = Renderer(drawn, cfg.domain, cfg.resolution, cfg.spp)
    render_threads = set_drjit_threads(0)  # the CPUs this process may use, set (and recorded) rather than left implicit
    if cfg.camera:
        from risp_data.diff_render import set_camera

        set_camera(renderer, read_camera(cfg.camera))
    frame_seeds = rng.integers(0, 2**31 - 1, cfg.frames)
    images = np.stack([renderer.render_reference(s, look, int(sd)) for s, sd in
                       tqdm(list(zip(env_states, frame_seeds)), desc="rendering", disable=not cfg.progress, leave=False)])
    try:  # without --overwrite published only where nothing is by then (another make-video may have written it)
        video_sha = write_video(cfg.out, images, cfg.fps, overwrite=cfg.overwrite,
                                comment=made_by(cfg.env, cfg.seed), exclusive=not cfg.overwrite)
    except FileExistsError:
        raise RispError(f"{cfg.out}: exists (written by another process while this one rendered); give another "
                        "--out, or --overwrite to replace it") from None
    # the video's files are a set: the truth names its video by checksum (tasks refuse a truth of another video),
    # and a replaced video's old truth and actions go before the new ones are written (a cube video has no actions)
    for stale in (truth_path(cfg.out), actions_path(cfg.out)):
        if os.path.exists(stale):
            os.remove(stale)
    truth = {"format": "risp-reference-truth", "format_version": 1, "env": cfg.env, "seed": cfg.seed,
             "video_sha256": video_sha, "versions": versions(),  # of the frames written, not the file there now
             "config": asdict(cfg), "fps": cfg.fps, "frames": cfg.frames, "sim_steps_per_frame": k, "dt": sim.dt,
             "params": dict(zip(sim.param_names, params[0].tolist())), "effects": list(sim.effects),
             "env_state_names": list(get_env_state_names(cfg.env)), "env_states": env_states.tolist(),
             "sim_state_names": list(sim.state_names) if len(sim.state_names) <= 64 else None,
             "sim_states": full.numpy().tolist() if len(sim.state_names) <= 64 else None,
             "actions": None if actions is None else np.asarray(actions).tolist(),
             "look": {"domain": cfg.domain, "psi": look.psi.tolist(), "aux": look.aux},
             "frame_seeds": frame_seeds.tolist(), "threads": {"torch": torch_threads, "drjit": render_threads},
             "outside_sampled_states": outside_sampled_states(cfg.env, env_states),
             "mesh": None if cfg.mesh is None else {"path": cfg.mesh, "sha256": sha256_file(cfg.mesh)}}
    if actions is not None:
        write_actions(actions_path(cfg.out), cfg.env, actions, cfg.fps)
        truth["actions_path"] = actions_path(cfg.out)
    write_text_atomic(truth_path(cfg.out), json.dumps(truth, indent=1))
    truth["truth_path"] = truth_path(cfg.out)
    return truth


def get_env_state_names(env: str):
    from risp_data.envs import get_environment

    return get_environment(env).state_names
