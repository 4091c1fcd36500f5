"""Measured trajectories <-> simulator states, observation channels and actions.

The simulators (risp_tasks.sims) expose their state layout by name (``sim.state_names``); measured files
carry a rigid-body pose, velocities and (quadrotor) rotor thrusts in newtons.  This module is the one place
that maps between them:

* ``sim_states``: measured sample -> full simulator state (by name; quaternion or Euler attitude).
* ``observe``: simulator state -> the observation channels compared with measurements
  (position, attitude as a rotation vector, linear velocity, body angular velocity).
* ``sim_actions``: measured commands -> the simulator's action units via its thrust mapping
  (``sim.thrust_to_action`` when the simulator provides one, else identity = newtons).
* ``substeps``: how many simulator steps make one measured sample interval (docs/diagnose.md §Time step).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from risp_data.errors import RispError

from ..measured import Trajectory

#: Observation channels of rigid-body environments (cube, quadrotor), in order.
RIGID_CHANNELS = ("x", "y", "z", "rx", "ry", "rz", "vx", "vy", "vz", "wx", "wy", "wz")
#: Channel groups share one noise level and one unit.
RIGID_GROUPS = {"position": (0, 1, 2), "attitude": (3, 4, 5), "velocity": (6, 7, 8), "angular velocity": (9, 10, 11)}
GROUP_UNITS = {"position": "m", "attitude": "rad", "velocity": "m/s", "angular velocity": "rad/s"}

_QUAT = ("qw", "qx", "qy", "qz")
_EULER = ("yaw", "pitch", "roll")


def matched_simulator(sim, sample_dt: float):
    """``(sim, k)`` with ``k`` steps of a simulator whose step is fixed (those without a ``dt`` option: the hand and
    the rod integrate with their module's DT) per sample interval Δ; RispError when k·dt misses Δ by more than the
    tasks' frame rule allows (``risp_tasks.sims.whole_steps``).  (It used to set ``sim.spec.dt`` to Δ/k, which these
    simulators never read: a 30 Hz log was simulated at 3 × 10 ms = 30 ms per 33.3 ms sample, silently.)"""
    from ..sims import STEP_TOLERANCE, step_rates, whole_steps

    k = whole_steps(sim, sample_dt)
    if k is None:
        raise RispError(f"the {sim.env} simulator steps a fixed {sim.dt:g} s: the data's sample interval "
                        f"{sample_dt:.6g} s is not a whole number of steps (within {STEP_TOLERANCE:.1%}); resample "
                        f"the data to a multiple of {sim.dt:g} s ({step_rates(sim)}, … Hz)")
    return sim, k


def _quat_from_euler_np(ypr: np.ndarray) -> np.ndarray:
    y, p, r = ypr[..., 0] / 2, ypr[..., 1] / 2, ypr[..., 2] / 2
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    return np.stack([cy * cp * cr + sy * sp * sr, cy * cp * sr - sy * sp * cr, cy * sp * cr + sy * cp * sr, sy * cp * cr - cy * sp * sr], -1)


def _euler_from_quat_np(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.moveaxis(q, -1, 0)
    yaw = np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))
    pitch = np.arcsin(np.clip(-2 * (x * z - w * y), -1, 1))
    roll = np.arctan2(2 * (y * z + w * x), 1 - 2 * (x * x + y * y))
    return np.stack([yaw, pitch, roll], -1)


def measured_columns(traj: Trajectory) -> dict[str, np.ndarray]:
    """All named per-sample quantities of a measured trajectory (N,) each."""
    cols = {"t": traj.t}
    if traj.pos is None:
        cols.update(traj.extra)
        return cols
    for i, c in enumerate(("x", "y", "z")):
        cols[c] = traj.pos[:, i]
    for i, c in enumerate(_QUAT):
        cols[c] = traj.quat[:, i]
    for i, c in enumerate(("vx", "vy", "vz")):
        cols[c] = traj.vel[:, i]
    for i, c in enumerate(("wx", "wy", "wz")):
        cols[c] = traj.omega[:, i]
    ypr = _euler_from_quat_np(traj.quat)
    for i, c in enumerate(_EULER):
        cols[c] = ypr[:, i]
    if traj.thrust is not None:
        for i in range(traj.thrust.shape[1]):
            cols[f"f{i}"] = traj.thrust[:, i]
    cols.update(traj.extra)
    return cols


def sim_states(sim, traj: Trajectory, actions: np.ndarray | None = None) -> np.ndarray:
    """(N, X) simulator states of every measured sample (float64).

    State entries without a measured counterpart: motor/rotor thrust states (names starting with ``f``
    or ``thrust``) are set to the commanded thrust of that sample (steady state); anything else is an
    error naming the state.
    """
    cols = measured_columns(traj)
    out = np.zeros((traj.n, len(sim.state_names)))
    for j, name in enumerate(sim.state_names):
        if name in cols:
            out[:, j] = cols[name]
            continue
        idx = _rotor_index(name)
        if idx is not None and actions is not None and idx < actions.shape[1]:
            out[:, j] = actions[:, idx]
            continue
        raise RispError(f"the {sim.env} simulator's state {name!r} has no measured counterpart (diagnose adapter)")
    return out


def _is_rate(name: str) -> bool:
    """Velocity-like state names: ``thumb_0_vel`` (hand), ``n1_0_0.vx`` (rod), ``v…``/``…_dot``."""
    leaf = name.rsplit(".", 1)[-1]
    return name.endswith(("_vel", "_dot", "_rate")) or leaf.startswith("v")


def _rotor_index(name: str) -> int | None:
    for prefix in ("thrust", "motor", "rotor", "f", "u"):
        if name.startswith(prefix):
            rest = name[len(prefix):].lstrip("_")
            if rest.isdigit():
                return int(rest)
    return None


def sim_actions(sim, traj: Trajectory, base_params: torch.Tensor | None = None) -> np.ndarray | None:
    """(N, A) actions in the simulator's units, or None for passive environments.

    Quadrotor thrusts are in newtons; a simulator whose action is not a thrust in newtons exposes
    ``thrust_to_action(thrust (…, 4) N, params) -> action`` and it is used here.
    """
    if sim.action_dim == 0:
        return None
    if traj.command is not None:
        # normalised rotor commands u ∈ [0, 1] are the simulator's action; its k_f (N per unit command,
        # fitted: candidates.build_model) is the thrust map f = k_f·u (docs/measured-data.md §Conventions).
        # The translational model's action is (collective, measured attitude quaternion).
        if traj.command.shape[1] == 1:
            # the attitude held over sample i is the midpoint one, normalise(q_i + q_{i+1}) (second order;
            # the commands themselves are a zero-order hold)
            q = traj.quat.copy()
            q[:-1] = q[:-1] + traj.quat[1:]
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            return np.concatenate([traj.command, q], 1)
        return traj.command
    if traj.thrust is not None:
        f = traj.thrust
        p = base_params if base_params is not None else sim.default_params(1)[0]
        conv = getattr(sim, "thrust_to_action", None)
        if conv is not None:
            a = conv(torch.as_tensor(f, dtype=torch.float64), p.reshape(1, -1).expand(len(f), -1))
            return np.asarray(a.detach().numpy(), dtype=np.float64)
        if "k_f" in sim.param_names:
            # the quadrotor's thrust mapping f_i = k_f · u_i (docs/models.md §2.2), inverted at the
            # model's own k_f so that the simulated thrust equals the measured one in newtons
            return f / float(p.reshape(-1)[sim.param_index("k_f")])
        if f.shape[1] != sim.action_dim:
            raise RispError(f"{traj.path}: {f.shape[1]} thrust columns but the simulator takes {sim.action_dim} actions")
        return f
    names = [f"u{i}" for i in range(sim.action_dim)]
    missing = [n for n in names if n not in traj.extra]
    if missing:
        raise RispError(f"{traj.path}: missing action column(s) {', '.join(missing)}")
    return np.stack([traj.extra[n] for n in names], 1)


def consistent_start(sim, s0: torch.Tensor) -> torch.Tensor:
    """Start states made consistent with the contact model (docs/diagnose.md §Start states).

    Cube: measurement noise of a fraction of a millimetre pushes a resting corner into the floor, and the
    stiff penalty contact (k_n ≈ 10⁶ N/m) turns that into a violent pop-up that is not in the data.  The
    cube is lifted so that its lowest corner penetrates by no more than the static penetration
    m·g/(4·k_n) of the default stiffness.  Other environments: unchanged.
    """
    if sim.env != "cube" or not hasattr(sim, "side"):
        return s0
    import itertools

    half = 0.5 * float(sim.side)
    corners = torch.tensor(list(itertools.product((-half, half), repeat=3)), dtype=s0.dtype)  # (8, 3)
    q = s0[:, 3:7] / s0[:, 3:7].norm(dim=1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    row2 = torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)  # world z of body axes
    lowest = s0[:, 2] + (corners @ row2.T).min(0).values  # (B,)
    rest = float(sim.mass) * 9.81 / (4 * 1e6)
    lift = torch.clamp(-lowest - rest, min=0.0)
    out = s0.clone()
    out[:, 2] = s0[:, 2] + lift
    return out


def lowest_corner_height(traj: Trajectory) -> np.ndarray:
    """(N,) height of the cube's lowest corner: z − (side/2)·Σ_j |R_zj| (R_zj: world z of body axis j)."""
    half = 0.5 * float(traj.sidecar.get("side"))
    w, x, y, z = traj.quat.T
    row2 = np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1)
    return traj.pos[:, 2] - half * np.abs(row2).sum(1)


#: Resting frames for the floor calibration: speed and angular speed below these.
REST_SPEED = 0.05  # m/s
REST_ANGULAR_SPEED = 0.5  # rad/s
MIN_REST_FRAMES = 20


def calibrate_floor(trajs: list[Trajectory], offset: float | str = "auto",
                    estimate_from: list[Trajectory] | None = None) -> tuple[list[Trajectory], dict]:
    """Cube only: shift measured heights so the floor is at z = 0 (docs/measured-data.md §Floor).

    ``auto``: the median lowest-corner height over resting frames (speed < 5 cm/s, |ω| < 0.5 rad/s) of
    ``estimate_from`` (default ``trajs``; diagnose passes its fitting part, so held-out data decide nothing) is
    the floor's height in the motion-capture frame (the real tosses rest ≈ 0.9 mm low); needs at least
    20 resting frames, else no shift.  A number: that offset [m].  The shift (of every trajectory in ``trajs``) is
    reported.
    """
    if trajs[0].sidecar.env != "cube":
        return trajs, {"applied": False}
    if offset == "auto":
        low = []
        for tr in (trajs if estimate_from is None else estimate_from):
            rest = (np.linalg.norm(tr.vel, axis=1) < REST_SPEED) & (np.linalg.norm(tr.omega, axis=1) < REST_ANGULAR_SPEED)
            low.append(lowest_corner_height(tr)[rest])
        low = np.concatenate(low) if low else np.zeros(0)
        if low.size < MIN_REST_FRAMES:
            return trajs, {"applied": False, "mode": "auto", "rest_frames": int(low.size)}
        value = float(np.median(low))
        info = {"applied": True, "mode": "auto", "rest_frames": int(low.size), "floor_offset_m": value}
    else:
        value = float(offset)
        info = {"applied": True, "mode": "given", "floor_offset_m": value}
    out = []
    for tr in trajs:
        pos = tr.pos.copy()
        pos[:, 2] -= value
        out.append(dataclasses.replace(tr, pos=pos))
        if info["mode"] == "given":  # the reader's own check, after the shift: a cube sunk in the floor is a wrong offset
            side, low = float(tr.sidecar.get("side")), float(lowest_corner_height(out[-1]).min())
            if low < -side:
                raise RispError(f"--floor-offset {value:g}: {tr.path} would go {-low:g} m below the floor, more than a "
                                f"side ({side:g} m): the offset is the floor's height in the data's frame [m]")
    return out, info


# ------------------------------------------------------------------------------------------------
# observation channels (torch, differentiable)
# ------------------------------------------------------------------------------------------------
class Observer:
    """Maps simulator states (..., X) to observation channels (..., C) and measures their errors."""

    def __init__(self, sim):
        names = list(sim.state_names)
        self.names = names
        self.rigid = all(n in names for n in ("x", "y", "z", "vx", "vy", "vz", "wx", "wy", "wz")) and (
            all(n in names for n in _QUAT) or all(n in names for n in _EULER)
        )
        if self.rigid:
            self.channels = RIGID_CHANNELS
            self.groups = RIGID_GROUPS
            self.i_pos = [names.index(n) for n in ("x", "y", "z")]
            self.i_vel = [names.index(n) for n in ("vx", "vy", "vz")]
            self.i_om = [names.index(n) for n in ("wx", "wy", "wz")]
            self.quat = all(n in names for n in _QUAT)
            self.i_att = [names.index(n) for n in (_QUAT if self.quat else _EULER)]
        else:
            # generalised coordinates and their rates: one noise level per kind; latent effect states
            # (appended after the base state, e.g. a motor-lag thrust) are not observed
            latent = {n for e in sim.spec.available_effects.values() for n in e.state_names}
            names = [n for n in names if n not in latent]
            self.channels = tuple(names)
            rate = [i for i, n in enumerate(names) if _is_rate(n)]
            coord = [i for i in range(len(names)) if i not in rate]
            self.groups = {g: tuple(idx) for g, idx in (("coordinate", coord), ("rate", rate)) if idx}

    def quaternion(self, s: torch.Tensor) -> torch.Tensor:
        a = s[..., self.i_att]
        if self.quat:
            return a / a.norm(dim=-1, keepdim=True)
        from risp_data.envs.rotations import euler_to_quat

        return euler_to_quat(a[..., 0], a[..., 1], a[..., 2])

    def error(self, pred: torch.Tensor, meas: torch.Tensor) -> torch.Tensor:
        """pred − meas per channel (..., C); attitude as the rotation vector 2·Im(q_meas* ⊗ q_pred)."""
        if not self.rigid:
            C = len(self.channels)
            return pred[..., :C] - meas[..., :C]
        qp, qm = self.quaternion(pred), self.quaternion(meas)
        w1, x1, y1, z1 = qm[..., 0], -qm[..., 1], -qm[..., 2], -qm[..., 3]  # q_meas*
        w2, x2, y2, z2 = qp.unbind(-1)
        rel = torch.stack(
            [
                w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            ],
            -1,
        )
        sign = torch.where(rel[..., :1] < 0, -1.0, 1.0).to(rel.dtype)
        rot = 2.0 * sign * rel[..., 1:]
        return torch.cat([pred[..., self.i_pos] - meas[..., self.i_pos], rot, pred[..., self.i_vel] - meas[..., self.i_vel],
                          pred[..., self.i_om] - meas[..., self.i_om]], -1)

    def group_of_channel(self) -> list[str]:
        out = [""] * len(self.channels)
        for g, idx in self.groups.items():
            for i in idx:
                out[i] = g
        return out


__all__ = ["Observer", "matched_simulator", "measured_columns", "sim_actions", "sim_states"]
