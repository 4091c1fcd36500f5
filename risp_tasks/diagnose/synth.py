"""Synthetic measured data with a hidden effect (docs/diagnose.md §Synthetic data) — for tests and benchmarks.

Trajectories are simulated by the real simulator with one library effect switched on (or none), written
as measured CSVs + sidecars exactly like real data, with white measurement noise added.

* effect magnitude: every parameter of the hidden effect = its library default × f, one factor
  f ~ U(0.5, 1.5) per trajectory set (drawn from the seed), clipped to the effect's plausible range;
* "unlisted" effects that are NOT in any simulator's library (so diagnose must answer ``unexplained``):
  ``periodic_force`` — a world-frame force A·m·g·sin(2π t / T) along x and y (A = 0.3 quadrotor, 0.6 cube);
  ``stiffness_error`` — the hand's joint stiffness 1.6× the simulator's fixed value (a wrong base
  parameter that diagnose does not fit);
* quadrotor: a geometric position/attitude controller tracks a random smooth reference (heights down to
  0.1 m so ground effect shows, horizontal reference speeds peaking at 1.5–6 m/s per axis so drag shows, a
  varying command so motor lag shows);
  the controller's rotor thrusts [N] are the measured commands f0…f3;
* cube: random tosses from 0.15–0.35 m with random linear and angular velocities;
* hand: random smooth finger torques.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from risp_data.errors import RispError

from ..sims.quadrotor_control import tracking_thrusts

from ..measured import write_trajectory_csv
from . import candidates as cands
from risp_data.atomic import write_text_atomic

#: Default measurement noise (1-σ) per channel group, SI units: typical motion-capture levels.
DEFAULT_NOISE = {
    "quadrotor": {"position": 5e-4, "attitude": 1e-3, "velocity": 5e-3, "angular velocity": 1e-2},
    "cube": {"position": 3e-4, "attitude": 1e-3, "velocity": 5e-3, "angular velocity": 2e-2},
    "hand": {"coordinate": 1e-3, "rate": 1e-2},
    "rod": {"coordinate": 1e-4, "rate": 1e-3},
}
MAGNITUDE_FACTOR = (0.5, 1.5)
UNLISTED = ("periodic_force", "stiffness_error")
STIFFNESS_ERROR = 1.6  # hand: true joint stiffness = 1.6 × the simulator's (fixed) default
PERIODIC_AMPLITUDE = {"quadrotor": 0.3, "cube": 0.6}  # × m·g
PERIODIC_PERIOD = 0.8  # s

GENERIC_ACTION_AMPLITUDE = {"hand": (0.1, 0.4), "rod": (20.0, 60.0)}  # N·m per finger; N on the rod's centre

QUAD_SIDECAR = {"env": "quadrotor", "mass": 3.0, "arm_length": 0.3, "rotor_layout": "+", "gravity": 9.81,
                "yaw_torque_coefficient": 0.02, "quaternion_order": "wxyz", "angular_velocity_frame": "body"}
CUBE_SIDECAR = {"env": "cube", "side": 0.1048, "mass": 0.37, "gravity": 9.81}


@dataclass(frozen=True)
class SynthConfig:
    env: str
    seed: int
    n_traj: int = 4
    samples: int = 200
    effect: str | None = None  # a library effect, "random", None (null case) or an UNLISTED name
    factor: float | None = None  # magnitude factor (None: drawn from MAGNITUDE_FACTOR)
    noise_scale: float = 1.0  # × DEFAULT_NOISE


def draw_effect(env: str, rng: np.random.Generator, effect: str | None, factor: float | None):
    """(effect name or None, {param: value}) of the hidden effect."""
    lib = cands.effect_names(env)
    if effect == "random":
        effect = str(rng.choice(list(lib)))
    if effect is None or effect in UNLISTED:
        return effect, {}
    if effect not in lib:
        raise RispError(f"unknown effect {effect!r} for {env}; choose from: {', '.join(lib + UNLISTED)}")
    from risp_tasks.sims import available_effects

    eff = available_effects(env)[effect]
    f = float(rng.uniform(*MAGNITUDE_FACTOR)) if factor is None else float(factor)
    vals = {f"{effect}.{p}": float(np.clip(d * f, lo, hi)) for p, d, (lo, hi) in zip(eff.param_names, eff.defaults, eff.ranges)}
    return effect, vals


def _sim_and_params(env: str, effect: str | None, values: dict, sidecar: dict, dt: float):
    from ..measured import Sidecar

    sc = Sidecar(env=env, values=sidecar, source="synthetic")
    effects = (effect,) if effect and effect not in UNLISTED else ()
    model, k = cands.build_model(env, effects, sc, dt)
    p = model.base.clone()
    for n, v in values.items():
        p[model.sim.param_index(n)] = v
    if effect == "stiffness_error":
        if env != "hand":
            raise RispError(f"stiffness_error is defined for the hand only, not {env}")
        for i, n in enumerate(model.sim.param_names):
            if n.startswith("stiffness_"):
                p[i] *= STIFFNESS_ERROR
    return model.sim, p, k


# ------------------------------------------------------------------------------------------------
# quadrotor: closed-loop flights
# ------------------------------------------------------------------------------------------------
def _simulate_quadrotor(sim, params, k, n_traj, samples, dt, rng, periodic: bool):
    B = n_traj
    mass = float(params[sim.param_index("mass")])
    inertia = params[[sim.param_index(n) for n in ("Ixx", "Iyy", "Izz")]]
    k_m = float(params[sim.param_index("k_m")])
    k_f = float(params[sim.param_index("k_f")])
    from risp_data.envs.quadrotor import ARM_LENGTH

    t = np.arange(samples) * dt
    amp = rng.uniform([0.8, 0.8, 0.25], [1.6, 1.6, 0.45], size=(B, 3))  # m; at 0.3–0.6 Hz: peaks of 1.5–6 m/s (x, y), 0.5–1.7 m/s (z)
    freq = rng.uniform(0.3, 0.6, size=(B, 3))
    phase = rng.uniform(0, 2 * math.pi, size=(B, 3))
    centre = np.concatenate([rng.uniform(-0.5, 0.5, size=(B, 2)), rng.uniform(0.35, 0.55, size=(B, 1))], 1)
    ref_p = centre[:, None] + amp[:, None] * np.sin(2 * math.pi * freq[:, None] * t[None, :, None] + phase[:, None])
    ref_v = amp[:, None] * 2 * math.pi * freq[:, None] * np.cos(2 * math.pi * freq[:, None] * t[None, :, None] + phase[:, None])
    ref_p = torch.tensor(ref_p)
    ref_v = torch.tensor(ref_v)
    ref_p[..., 2] = torch.clamp(ref_p[..., 2], min=0.1)
    s = torch.zeros(B, len(sim.state_names), dtype=torch.float64)
    s[:, 0:3] = ref_p[:, 0]
    s[:, 3] = 1.0
    s[:, 7:10] = ref_v[:, 0]
    if len(sim.state_names) > 13:  # motor-lag thrust states at hover
        s[:, 13:17] = mass * 9.81 / 4
    P = params.unsqueeze(0).expand(B, -1)
    states, thrusts = [s], []
    with torch.no_grad():
        for i in range(samples - 1):
            f = tracking_thrusts(s, ref_p[:, i], ref_v[:, i], mass, inertia, k_m, ARM_LENGTH)
            thrusts.append(f)
            for j in range(k):
                s = sim.step(P, s, f / k_f, i * k + j)
                if periodic:
                    s = _add_periodic(s, (i * k + j + 1) * sim.dt, sim.dt, mass, 0.0, "quadrotor")
            states.append(s)
        thrusts.append(thrusts[-1])
    return torch.stack(states, 1).numpy(), torch.stack(thrusts, 1).numpy()


def _add_periodic(s: torch.Tensor, t: float, h: float, mass: float, rng_phase: float, env: str) -> torch.Tensor:
    """The unlisted effect: world force A·m·g·sin(2πt/T) along x and (phase-shifted) y, added to the step."""
    a = PERIODIC_AMPLITUDE[env] * 9.81 * torch.tensor([math.sin(2 * math.pi * t / PERIODIC_PERIOD + rng_phase),
                                                  math.cos(2 * math.pi * t / PERIODIC_PERIOD + rng_phase), 0.0],
                                                 dtype=s.dtype)
    s = s.clone()
    s[:, 7:10] += h * a
    s[:, 0:3] += h * h * a
    return s


# ------------------------------------------------------------------------------------------------
# cube: tosses
# ------------------------------------------------------------------------------------------------
def _simulate_cube(sim, params, k, n_traj, samples, dt, rng, periodic: bool):
    from risp_data.envs.rotations import euler_to_quat

    B = n_traj
    ypr = torch.tensor(rng.uniform(-math.pi, math.pi, size=(B, 3)) * np.array([1, 0.5, 1]))
    s = torch.zeros(B, 13, dtype=torch.float64)
    s[:, 0:2] = torch.tensor(rng.uniform(-0.2, 0.2, size=(B, 2)))
    s[:, 2] = torch.tensor(rng.uniform(0.15, 0.35, size=B))
    s[:, 3:7] = euler_to_quat(ypr[:, 0], ypr[:, 1], ypr[:, 2])
    s[:, 7:9] = torch.tensor(rng.uniform(-1.2, 1.2, size=(B, 2)))
    s[:, 9] = torch.tensor(rng.uniform(-1.0, 0.5, size=B))
    s[:, 10:13] = torch.tensor(rng.uniform(-8, 8, size=(B, 3)))
    P = params.unsqueeze(0).expand(B, -1)
    states = [s]
    with torch.no_grad():
        if not periodic:
            return sim.rollout(P, s, None, (samples - 1) * k)[:, ::k].numpy(), None
        for i in range(samples - 1):
            for j in range(k):
                s = sim.step(P, s, None, i * k + j)
                s = _add_periodic(s, (i * k + j + 1) * sim.dt, sim.dt, sim.mass, 0.0, "cube")
            states.append(s)
    return torch.stack(states, 1).numpy(), None


def _simulate_generic(sim, params, k, n_traj, samples, dt, rng):
    B, A = n_traj, sim.action_dim
    rest = getattr(sim, "rest_state", None)
    s = rest(B) if rest is not None else torch.zeros(B, len(sim.state_names), dtype=torch.float64)
    t = np.arange(samples) * dt
    freq = rng.uniform(0.3, 1.2, size=(B, 1, A))
    phase = rng.uniform(0, 2 * math.pi, size=(B, 1, A))
    amp = rng.uniform(*GENERIC_ACTION_AMPLITUDE.get(sim.env, (0.1, 0.4)), size=(B, 1, A))
    u = torch.tensor(amp * np.sin(2 * math.pi * freq * t[None, :, None] + phase))
    P = params.unsqueeze(0).expand(B, -1)
    states = [s]
    with torch.no_grad():
        for i in range(samples - 1):
            for j in range(k):
                s = sim.step(P, s, u[:, i], i * k + j)
            states.append(s)
    return torch.stack(states, 1).numpy(), u.numpy()


# ------------------------------------------------------------------------------------------------
def make_synthetic(cfg: SynthConfig, out_dir: str | os.PathLike) -> dict:
    """Write ``cfg.n_traj`` measured trajectories (CSV + sidecar) and ``truth.json``; returns the truth."""
    from risp_data.threads import torch_threads

    with torch_threads(1):  # tiny batched ops: see run.diagnose
        return _make_synthetic(cfg, out_dir)


def _make_synthetic(cfg: SynthConfig, out_dir: str | os.PathLike) -> dict:
    rng = np.random.default_rng(np.random.SeedSequence([int(cfg.seed), 7]))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    effect, values = draw_effect(cfg.env, rng, cfg.effect, cfg.factor)
    periodic = effect == "periodic_force"
    if cfg.env == "quadrotor":
        dt, sidecar = 0.01, dict(QUAD_SIDECAR)
    elif cfg.env == "cube":
        dt, sidecar = 1.0 / 148.0, dict(CUBE_SIDECAR)  # the real tosses' rate
    else:
        dt, sidecar = 0.01, {"env": cfg.env}
    sim, params, k = _sim_and_params(cfg.env, effect, values, sidecar, dt)
    if cfg.env == "quadrotor":
        states, acts = _simulate_quadrotor(sim, params, k, cfg.n_traj, cfg.samples, dt, rng, periodic)
    elif cfg.env == "cube":
        states, acts = _simulate_cube(sim, params, k, cfg.n_traj, cfg.samples, dt, rng, periodic)
    else:
        if periodic:
            raise RispError(f"periodic_force is not defined for {cfg.env}")
        states, acts = _simulate_generic(sim, params, k, cfg.n_traj, cfg.samples, dt, rng)
    noise = {g: v * cfg.noise_scale for g, v in DEFAULT_NOISE[cfg.env].items()}
    names = list(sim.state_names)
    for b in range(cfg.n_traj):
        x = states[b]
        cols = {"t": np.arange(cfg.samples) * dt}  # noqa: B023
        if cfg.env in ("quadrotor", "cube"):
            n = lambda shape, g: noise[g] * rng.standard_normal(shape)  # noqa: E731
            pos = x[:, 0:3] + n((cfg.samples, 3), "position")
            dq = np.concatenate([np.ones((cfg.samples, 1)), 0.5 * n((cfg.samples, 3), "attitude")], 1)
            from ..measured import quat_mul

            q = quat_mul(x[:, 3:7], dq)
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            vel = x[:, 7:10] + n((cfg.samples, 3), "velocity")
            om = x[:, 10:13] + n((cfg.samples, 3), "angular velocity")
            for i, c in enumerate("xyz"):
                cols[c] = pos[:, i]
            for i, c in enumerate(("qw", "qx", "qy", "qz")):
                cols[c] = q[:, i]
            for i, c in enumerate(("vx", "vy", "vz")):
                cols[c] = vel[:, i]
            for i, c in enumerate(("wx", "wy", "wz")):
                cols[c] = om[:, i]
            if acts is not None:
                for i in range(4):
                    cols[f"f{i}"] = acts[b, :, i]
        else:
            from .adapter import Observer

            obs = Observer(sim)
            for g, idx in obs.groups.items():
                for i in idx:
                    cols[names[i]] = x[:, i] + noise[g] * rng.standard_normal(cfg.samples)
            for i in range(sim.action_dim):
                cols[f"u{i}"] = acts[b, :, i]
        write_trajectory_csv(out / f"traj_{b:03d}.csv", cols, sidecar)
    truth = {"env": cfg.env, "effect": effect, "parameters": values, "noise": noise, "seed": int(cfg.seed),
             "n_traj": cfg.n_traj, "samples": cfg.samples, "dt": dt}
    write_text_atomic(out / "truth.json", json.dumps(truth, indent=2))
    return truth
