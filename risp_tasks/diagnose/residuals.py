"""Residual analysis (docs/diagnose.md §Residuals): what the model gets wrong, per channel, in SI units.

* one-step residuals: from every measured state x̃_i the model predicts one sample ahead; the velocity
  error divided by the sample interval Δ is the acceleration residual a_meas − a_model (m/s², rad/s²),
  i.e. the unmodelled specific force / angular acceleration; position/attitude errors are kept too.
* multi-step rollout error: from every segment start the model runs H_r samples open loop; the error at
  the last sample, RMS per channel group.
* candidate regressors per sample (speed, height, tilt, angular speed, total command, contact state,
  time) so that residuals can be plotted against them (a drag shows as a residual ∝ −v, ground effect as
  a residual rising near z = 0, a motor lag as a residual following the command's rate of change).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..measured import Trajectory
from .adapter import GROUP_UNITS, Observer, sim_actions, sim_states
from .fit import Segments, make_segments, predict


@dataclass
class OneStep:
    channels: tuple[str, ...]
    error: np.ndarray  # (M, C) one-step prediction error (SI units; attitude as rotation vector)
    accel: np.ndarray  # (M, C_rate) rate channels' error / Δ (acceleration residuals)
    accel_names: tuple[str, ...]
    t: np.ndarray  # (M,) time of the predicted sample
    traj: np.ndarray  # (M,) trajectory index
    regressors: dict[str, np.ndarray]  # name -> (M,)


def _rate_channels(obs: Observer) -> list[int]:
    if obs.rigid:
        return list(obs.groups["velocity"]) + list(obs.groups["angular velocity"])
    return list(obs.groups.get("rate", ()))


def regressors(sim, trajs: list[Trajectory], seg: Segments) -> dict[str, np.ndarray]:
    """Candidate regressors at each segment start."""
    out: dict[str, list[float]] = {}
    cache: dict[int, tuple] = {}
    obs = Observer(sim)
    rate = _rate_channels(obs)
    coord = [c for c in range(len(obs.channels)) if c not in rate]
    for j, i in zip(seg.traj_index, seg.start):
        tr = trajs[j]
        r: dict[str, float] = {"time [s]": float(tr.t[i])}
        if tr.pos is not None:
            r["speed [m/s]"] = float(np.linalg.norm(tr.vel[i]))
            r["height z [m]"] = float(tr.pos[i, 2])
            q = tr.quat[i]
            bz = 1 - 2 * (q[1] ** 2 + q[2] ** 2)  # world z of the body z axis
            r["tilt [rad]"] = float(np.arccos(np.clip(bz, -1, 1)))
            r["angular speed [rad/s]"] = float(np.linalg.norm(tr.omega[i]))
            if tr.sidecar.env == "cube":
                half = 0.5 * float(tr.sidecar.get("side"))
                # the lowest corner: centre height minus the largest vertical extent of the half-diagonal
                R = np.array([[1 - 2 * (q[2] ** 2 + q[3] ** 2), 2 * (q[1] * q[2] - q[0] * q[3]), 2 * (q[1] * q[3] + q[0] * q[2])],
                              [2 * (q[1] * q[2] + q[0] * q[3]), 1 - 2 * (q[1] ** 2 + q[3] ** 2), 2 * (q[2] * q[3] - q[0] * q[1])],
                              [2 * (q[1] * q[3] - q[0] * q[2]), 2 * (q[2] * q[3] + q[0] * q[1]), 1 - 2 * (q[1] ** 2 + q[2] ** 2)]])
                lowest = tr.pos[i, 2] - half * np.abs(R[2]).sum()
                r["lowest corner z [m]"] = float(lowest)
                r["contact"] = float(lowest < 0.005)
        cmd, unit = (tr.thrust, "N") if tr.thrust is not None else (tr.command, "1")
        if cmd is not None:
            label = "thrust" if unit == "N" else "command"
            r[f"total {label} [{unit}]"] = float(cmd[i].sum())
            prev = cmd[max(i - 1, 0)].sum()
            r[f"{label} rate [{unit}/s]"] = float((cmd[i].sum() - prev) / tr.dt)
        if tr.pos is None:
            if j not in cache:
                a = sim_actions(sim, tr)
                cache[j] = (sim_states(sim, tr, a), a)
            x, a = cache[j]
            r["|rate|"] = float(np.linalg.norm(x[i, rate])) if rate else 0.0
            r["|coordinate|"] = float(np.linalg.norm(x[i, coord])) if coord else 0.0
            if a is not None:
                r["|command|"] = float(np.linalg.norm(a[i]))
        for k, v in r.items():
            out.setdefault(k, []).append(v)
    return {k: np.asarray(v) for k, v in out.items()}


def _rng(seed: int, salt: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), 4, salt]))


def one_step(sim, obs: Observer, params: torch.Tensor, trajs: list[Trajectory], k: int,
             max_samples: int | None = None, seed: int = 0) -> OneStep:
    """One-step prediction errors from every measured sample (SI units); at most ``max_samples`` (a seeded
    subset, the same for every model of one run) so that scoring a huge log stays bounded."""
    # params: measured thrusts become commands at the model's own k_f (a sidecar may fix it), as in the fit
    seg = make_segments(sim, trajs, horizon=1, k=k, stride=1, max_segments=max_samples, rng=_rng(seed, 0),
                        params=params.reshape(-1))
    with torch.no_grad():
        pred = predict(sim, params, seg)
        err = obs.error(pred[:, 1], seg.meas[:, 1]).numpy()
    rate = _rate_channels(obs)
    t = np.array([trajs[j].t[i + 1] for j, i in zip(seg.traj_index, seg.start)])
    return OneStep(
        channels=tuple(obs.channels),
        error=err,
        accel=-err[:, rate] / seg.sample_dt,  # err = pred − meas, so −err/Δ = a_meas − a_model
        accel_names=tuple(f"a_{obs.channels[c]}" for c in rate),
        t=t,
        traj=seg.traj_index,
        regressors=regressors(sim, trajs, seg),
    )


def group_rms(obs: Observer, err: np.ndarray) -> dict[str, float]:
    """RMS of an error array (..., C) per channel group."""
    return {g: float(np.sqrt(np.mean(err[..., list(idx)] ** 2))) for g, idx in obs.groups.items()}


def accel_rms(obs: Observer, os_: OneStep) -> dict[str, float]:
    """RMS acceleration residual per rate group (m/s², rad/s²)."""
    out = {}
    rate = _rate_channels(obs)
    if obs.rigid:
        out["acceleration"] = float(np.sqrt(np.mean(os_.accel[:, :3] ** 2)))
        out["angular acceleration"] = float(np.sqrt(np.mean(os_.accel[:, 3:] ** 2)))
    elif rate:
        out["rate derivative"] = float(np.sqrt(np.mean(os_.accel**2)))
    return out


def rollout_error(sim, obs: Observer, params: torch.Tensor, trajs: list[Trajectory], k: int, horizon: int,
                  sigma=1.0, max_segments: int | None = None, seed: int = 0) -> dict:
    """Error after ``horizon`` open-loop samples from every non-overlapping segment start (at most
    ``max_segments``, a seeded subset): RMS per group (SI units, ``groups``) and the RMS over all channels
    in units of each channel's noise σ (``normalized``)."""
    seg = make_segments(sim, trajs, horizon=horizon, k=k, stride=horizon, max_segments=max_segments,
                        rng=_rng(seed, 1), params=params.reshape(-1))
    with torch.no_grad():
        pred = predict(sim, params, seg)
        err = obs.error(pred[:, -1], seg.meas[:, -1]).numpy()
    return {"groups": group_rms(obs, err), "normalized": float(np.sqrt(np.mean((err / sigma) ** 2)))}


#: the generalised coordinates' units: the hand's are joint angles, the rod's and the quadrotor's translational
#: mode's positions
COORDINATE_UNITS = {"hand": ("rad", "rad/s", "rad/s²")}


def unit_of(group: str, env: str | None = None) -> str:
    """The SI unit of a channel group (or of an acceleration-residual group) of ``env``'s observations."""
    if group in ("acceleration", "angular acceleration"):
        return "m/s²" if group == "acceleration" else "rad/s²"
    if group in ("coordinate", "rate", "rate derivative"):
        units = COORDINATE_UNITS.get(env, ("m", "m/s", "m/s²"))
        return units[("coordinate", "rate", "rate derivative").index(group)]
    return GROUP_UNITS.get(group, "")
