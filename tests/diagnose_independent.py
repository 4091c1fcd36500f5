"""An independent quadrotor flight generator for the diagnose acceptance tests (issue 12).

Written from the equations, not from risp_tasks.sims.quadrotor: numpy, classical RK4 at 1 kHz (the project's
simulator is semi-implicit Euler in torch), its own cascaded PD controller running at the sample rate
(zero-order hold of its rotor commands), and hidden effects implemented here:

    wind            F = (fx, fy, fz)                              world frame, constant [N]
    rotor_drag      F = −R·diag(dx, dy, dz)·Rᵀ·v                  linear drag in body axes [N s/m]
    air_drag        F = −c·|v|·v                                  quadratic drag [N s²/m²]
    motor_lag       ḟ_i = (f_cmd,i − f_i) / τ                     first-order rotors [s]
    ground_effect   f_i ← f_i·(1 + k·(R/(4 z_i))²), z_i = hub height (torques follow)
    ground_effect_centre  T ← T·(1 + k·(R/(4 z))²), z = centre height, no torque
    gust            F = A·m·g·(sin(2πt/1.3 s + φ), cos(2πt/0.9 s), 0)  (time-varying, not in the library)

Measurements: white noise (motion-capture levels) on position, attitude, velocity and body rates; the
written commands are the controller's rotor thrusts [N] (or, with ``px4=True``, PX4-like columns:
quaternion x,y,z,w, world-frame rates and normalised motor commands).
"""

from __future__ import annotations

import math

import numpy as np

G = 9.81
ROTOR_R = 0.12  # m (the rendered vehicle's rotor radius)
HUB_UP = 0.03  # m: rotor plane above the centre
NOISE = {"position": 5e-4, "attitude": 1e-3, "velocity": 5e-3, "angular velocity": 1e-2}


def qmul(a, b):
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def rotmat(q):
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


class Vehicle:
    def __init__(self, mass=3.0, inertia=(0.0583, 0.0583, 0.1099), arm=0.3, angles=None, spin=(1, -1, 1, -1), k_m=0.02):
        self.m, self.I, self.arm, self.k_m = mass, np.asarray(inertia, float), arm, k_m
        self.angles = np.asarray(angles if angles is not None else [i * math.pi / 2 for i in range(4)])
        self.spin = np.asarray(spin, float)
        self.hub = np.stack([arm * np.cos(self.angles), arm * np.sin(self.angles), np.full(4, HUB_UP)], 1)  # (4, 3)
        # [T, τx, τy, τz] = M f
        self.M = np.stack([np.ones(4), self.hub[:, 1], -self.hub[:, 0], k_m * self.spin])
        self.M_inv = np.linalg.inv(self.M)


def derivative(veh: Vehicle, x, f_cmd, t, effect, par):
    """ẋ of x = (p 3, q 4, v 3, ω 3, f 4) for a batch (B, 17)."""
    p, q, v, w, f = x[:, 0:3], x[:, 3:7], x[:, 7:10], x[:, 10:13], x[:, 13:17]
    R = rotmat(q)
    fdot = np.zeros_like(f)
    if effect == "motor_lag":
        fdot = (f_cmd - f) / par["tau"]
        thrust = f
    else:
        thrust = f_cmd
    if effect == "ground_effect":
        z_hub = p[:, 2:3] + np.einsum("bj,ij->bi", R[:, 2, :], veh.hub)
        thrust = thrust * (1 + par["k"] * (ROTOR_R / (4 * z_hub)) ** 2)
    T = thrust.sum(1)
    if effect == "ground_effect_centre":
        T = T * (1 + par["k"] * (ROTOR_R / (4 * p[:, 2])) ** 2)
    F = T[:, None] * R[:, :, 2] + np.array([0, 0, -veh.m * G])
    if effect == "wind":
        F = F + np.array([par["fx"], par["fy"], par["fz"]])
    if effect == "rotor_drag":
        vb = np.einsum("bji,bj->bi", R, v)
        F = F - np.einsum("bij,bj->bi", R, np.array([par["dx"], par["dy"], par["dz"]]) * vb)
    if effect == "air_drag":
        F = F - par["c"] * np.linalg.norm(v, axis=1, keepdims=True) * v
    if effect == "gust":
        A = par["amplitude"] * veh.m * G
        F = F + A * np.stack([np.sin(2 * math.pi * t / 1.3 + par["phase"]) + 0 * t, np.cos(2 * math.pi * t / 0.9) + 0 * t,
                              0 * t], -1)
    tau = np.stack([thrust @ veh.hub[:, 1], -(thrust @ veh.hub[:, 0]), veh.k_m * thrust @ veh.spin], 1)
    wdot = (tau - np.cross(w, veh.I * w)) / veh.I
    qdot = 0.5 * qmul(q, np.concatenate([np.zeros((len(q), 1)), w], 1))
    return np.concatenate([v, qdot, F / veh.m, wdot, fdot], 1)


def controller(veh: Vehicle, x, ref_p, ref_v, ref_a):
    """Cascaded PD: position -> desired acceleration -> thrust and tilt; attitude PD -> torques -> rotors."""
    p, q, v, w = x[:, 0:3], x[:, 3:7], x[:, 7:10], x[:, 10:13]
    acc = ref_a + 4.0 * (ref_p - p) + 3.0 * (ref_v - v)
    acc = np.clip(acc, -7, 7) + np.array([0, 0, G])
    R = rotmat(q)
    T = veh.m * np.einsum("bi,bi->b", acc, R[:, :, 2])
    z_des = acc / np.linalg.norm(acc, axis=1, keepdims=True)
    # desired attitude with zero yaw: the shortest rotation taking e_z to z_des
    axis = np.cross(np.array([0, 0, 1.0]), z_des)
    s = np.linalg.norm(axis, axis=1, keepdims=True)
    ang = np.arctan2(s, z_des[:, 2:3])
    q_des = np.concatenate([np.cos(ang / 2), np.sin(ang / 2) * axis / np.maximum(s, 1e-12)], 1)
    q_err = qmul(q * np.array([1, -1, -1, -1.0]), q_des)  # body-frame error rotation
    q_err *= np.sign(q_err[:, :1] + 1e-15)
    tau = veh.I * (50.0 * 2 * q_err[:, 1:] - 11.0 * w)
    f = np.einsum("ij,bj->bi", veh.M_inv, np.concatenate([T[:, None], tau], 1))
    return np.clip(f, 0.05 * veh.m * G / 4, 2.5 * veh.m * G / 4)


def fly(effect=None, par=None, seed=0, n=4, samples=300, dt=0.01, rate_hz=1000, veh: Vehicle | None = None, low=False):
    """(t (N,), states (B, N, 17), commands (B, N, 4)) of ``n`` closed-loop flights sampled every ``dt``."""
    veh = veh or Vehicle()
    par = par or {}
    rng = np.random.default_rng(seed)
    sub = int(round(dt * rate_hz))
    h = dt / sub
    t = np.arange(samples) * dt
    amp = rng.uniform([0.6, 0.6, 0.1], [1.0, 1.0, 0.15], size=(n, 3))
    if low:  # near the floor: gentler manoeuvres so that no rotor hub comes closer than ~5 cm
        amp = rng.uniform([0.3, 0.3, 0.08], [0.5, 0.5, 0.12], size=(n, 3))
    freq = rng.uniform(0.3, 0.45, size=(n, 3))
    ph = rng.uniform(0, 2 * math.pi, size=(n, 3))
    centre = np.concatenate([rng.uniform(-0.5, 0.5, (n, 2)), rng.uniform(0.24, 0.28, (n, 1)) if low else
                             rng.uniform(0.7, 1.0, (n, 1))], 1)
    om = 2 * math.pi * freq
    arg = om[:, None] * t[None, :, None] + ph[:, None]
    ref_p = centre[:, None] + amp[:, None] * np.sin(arg)
    ref_v = amp[:, None] * om[:, None] * np.cos(arg)
    ref_a = -amp[:, None] * om[:, None] ** 2 * np.sin(arg)
    x = np.zeros((n, 17))
    x[:, 0:3] = ref_p[:, 0]
    x[:, 3] = 1.0
    x[:, 7:10] = ref_v[:, 0]
    x[:, 13:17] = veh.m * G / 4
    states, cmds = [], []
    for i in range(samples):
        states.append(x.copy())
        f = controller(veh, x, ref_p[:, i], ref_v[:, i], ref_a[:, i])
        cmds.append(f)
        for j in range(sub):
            tt = t[i] + j * h
            k1 = derivative(veh, x, f, tt, effect, par)
            k2 = derivative(veh, x + 0.5 * h * k1, f, tt + h / 2, effect, par)
            k3 = derivative(veh, x + 0.5 * h * k2, f, tt + h / 2, effect, par)
            k4 = derivative(veh, x + h * k3, f, tt + h, effect, par)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            x[:, 3:7] /= np.linalg.norm(x[:, 3:7], axis=1, keepdims=True)
        z_hub = x[:, 2:3] + np.einsum("bj,ij->bi", rotmat(x[:, 3:7])[:, 2, :], veh.hub)
        if not np.isfinite(x).all() or (z_hub < 0.03).any():
            raise RuntimeError(f"independent generator: flight crashed at sample {i}")
    return t, np.stack(states, 1), np.stack(cmds, 1)


def measured(t, states, seed, noise=NOISE, phi=0.0):
    """Per flight: dict of measured columns (scalar-first quaternion, body rates) with white noise, or AR(1)
    noise of lag-1 correlation ``phi`` (what a filter leaves)."""
    rng = np.random.default_rng(seed + 1000)

    def draw(shape):
        e = rng.standard_normal(shape)
        for i in range(1, shape[0]):
            e[i] = phi * e[i - 1] + math.sqrt(1 - phi * phi) * e[i]
        return e

    out = []
    for b in range(states.shape[0]):
        s = states[b]
        N = len(t)
        d = noise["attitude"] * draw((N, 3))
        q = qmul(s[:, 3:7], np.concatenate([np.ones((N, 1)), 0.5 * d], 1))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        q *= np.sign(q[:, :1])
        cols = {"t": t}
        for i, c in enumerate("xyz"):
            cols[c] = s[:, i] + noise["position"] * draw((N,))
        for i, c in enumerate(("qw", "qx", "qy", "qz")):
            cols[c] = q[:, i]
        for i, c in enumerate(("vx", "vy", "vz")):
            cols[c] = s[:, 7 + i] + noise["velocity"] * draw((N,))
        for i, c in enumerate(("wx", "wy", "wz")):
            cols[c] = s[:, 10 + i] + noise["angular velocity"] * draw((N,))
        out.append(cols)
    return out


SIDECAR = {"env": "quadrotor", "mass": 3.0, "inertia": [0.0583, 0.0583, 0.1099], "arm_length": 0.3,
           "rotor_layout": "+", "yaw_torque_coefficient": 0.02, "gravity": 9.81,
           "angular_velocity_frame": "body"}


def write_flights(folder, effect=None, par=None, seed=0, n=4, samples=300, low=None, phi=0.0, sidecar=None):
    """Fly, add noise, write CSV + sidecar per flight (docs/measured-data.md); returns the folder."""
    from risp_tasks.measured import write_trajectory_csv

    low = effect in ("ground_effect", "ground_effect_centre") if low is None else low
    t, states, cmds = fly(effect, par, seed=seed, n=n, samples=samples, low=low)
    folder.mkdir(parents=True, exist_ok=True)
    for b, cols in enumerate(measured(t, states, seed, phi=phi)):
        for i in range(4):
            cols[f"f{i}"] = cmds[b, :, i]
        write_trajectory_csv(folder / f"flight_{b}.csv", cols, sidecar or SIDECAR)
    return folder


#: A PX4-like quad-X: motors 1..4 = front-right, rear-left, front-left, rear-right (x forward, y left, z up),
#: 1 and 2 counter-clockwise; 0.16 m arms, 2.6 kg.
PX4_ANGLES_DEG = (-45.0, 135.0, 45.0, -135.0)
PX4_SPIN = (1, 1, -1, -1)
PX4_FULL_THRUST = 12.0  # N per rotor at command 1 (the true thrust map f = 12·u)
PX4_SIDECAR = {"env": "quadrotor", "mass": 2.6, "inertia": [0.025, 0.025, 0.045], "arm_length": 0.16,
               "rotor_layout": "x", "rotor_angles_deg": list(PX4_ANGLES_DEG), "rotor_spin": list(PX4_SPIN),
               "yaw_torque_coefficient": 0.016, "quaternion_order": "xyzw", "angular_velocity_frame": "world",
               "actuator": "pwm", "pwm_range": [1000, 2000], "hover_throttle": 0.55}


def write_px4_flights(folder, wind, seed=0, n=4, samples=300, collective=False, quadratic=None):
    """Flights of the PX4-like vehicle in a constant wind, logged in PX4-like conventions: header
    t,x,y,z,vx,vy,vz,qx,qy,qz,qw (scalar last), world-frame rates, per-motor PWM in [1000, 2000] µs — or,
    with ``collective``, only the normalised collective throttle Σf / (4·12 N) (translational mode).
    ``quadratic`` = (a, b): the motors' thrust map is f = a·u + b·u² instead of 12·u."""
    from risp_tasks.measured import write_trajectory_csv

    veh = Vehicle(mass=2.6, inertia=(0.025, 0.025, 0.045), arm=0.16, angles=np.radians(PX4_ANGLES_DEG),
                  spin=PX4_SPIN, k_m=0.016)
    t, states, cmds = fly("wind", dict(zip(("fx", "fy", "fz"), wind)), seed=seed, n=n, samples=samples, veh=veh)
    folder.mkdir(parents=True, exist_ok=True)
    for b, cols in enumerate(measured(t, states, seed)):
        q = np.stack([cols[c] for c in ("qw", "qx", "qy", "qz")], 1)
        w_world = np.einsum("nij,nj->ni", rotmat(q), np.stack([cols[c] for c in ("wx", "wy", "wz")], 1))
        out = {k: cols[k] for k in ("t", "x", "y", "z", "vx", "vy", "vz", "qx", "qy", "qz", "qw")}
        out.update(wx=w_world[:, 0], wy=w_world[:, 1], wz=w_world[:, 2])
        if collective:
            out["throttle"] = cmds[b].sum(1) / (4 * PX4_FULL_THRUST)
            sidecar = {k: v for k, v in PX4_SIDECAR.items() if k != "pwm_range"}
            sidecar["actuator"] = "collective_normalized"
        elif quadratic is not None:
            qa, qb = quadratic
            for i in range(4):
                u = (-qa + np.sqrt(qa * qa + 4 * qb * cmds[b, :, i])) / (2 * qb)
                out[f"pwm{i}"] = 1000.0 + 1000.0 * u
            sidecar = {**PX4_SIDECAR, "thrust_map": "quadratic"}
        else:
            for i in range(4):
                out[f"pwm{i}"] = 1000.0 + 1000.0 * cmds[b, :, i] / PX4_FULL_THRUST
            sidecar = PX4_SIDECAR
        write_trajectory_csv(folder / f"log_{b}.csv", out, sidecar)
    return folder
