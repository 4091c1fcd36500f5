"""A geometric tracking controller for the quadrotor (Lee, Leok, McClamroch 2010), in the simulator's conventions.

Used to fly reference paths: the synthetic flights of ``diagnose`` (risp_tasks/diagnose/synth.py), the reference
videos of ``make-video`` and the tracking initialisation of ``imitate`` (risp_tasks/tasks/).
"""

from __future__ import annotations

import torch


KP, KD = 4.0, 3.0  # position and velocity gains of the commanded acceleration [1/s², 1/s]


def tracking_thrusts(state: torch.Tensor, ref_p, ref_v, mass: float, inertia: torch.Tensor, k_m: float, arm: float,
                     integral=None, ki: float = 0.0):
    """Geometric controller (Lee et al. 2010) -> rotor thrusts (B, 4) in newtons.

    Commanded acceleration a_des = KP·(p_ref − p) + KD·(v_ref − v) + ki·∫(p_ref − p) dt (``integral``: that
    integral, kept by the caller; the I term lets a steady disturbance be compensated by the commands).
    """
    from risp_data.envs.rotations import quat_to_matrix

    g = 9.81
    p, q, v, w = state[:, 0:3], state[:, 3:7], state[:, 7:10], state[:, 10:13]
    a_des = KP * (ref_p - p) + KD * (ref_v - v)
    if integral is not None:
        a_des = a_des + ki * integral
    a_des = torch.clamp(a_des, -6, 6)
    a_des[:, 2] += g
    R = quat_to_matrix(q)
    T = mass * (a_des * R[:, :, 2]).sum(1)
    zd = a_des / a_des.norm(dim=1, keepdim=True)
    xc = torch.tensor([1.0, 0.0, 0.0], dtype=state.dtype).expand_as(zd)
    yd = torch.linalg.cross(zd, xc)
    yd = yd / yd.norm(dim=1, keepdim=True)
    xd = torch.linalg.cross(yd, zd)
    Rd = torch.stack([xd, yd, zd], -1)
    E = Rd.transpose(1, 2) @ R - R.transpose(1, 2) @ Rd
    e_R = 0.5 * torch.stack([E[:, 2, 1], E[:, 0, 2], E[:, 1, 0]], 1)
    tau = inertia * (-60.0 * e_R - 12.0 * w)
    # T = Σf, τx = L(f1 − f3), τy = L(f2 − f0), τz = k_m(f0 − f1 + f2 − f3)
    Mx = torch.tensor([[1.0, 1, 1, 1], [0, arm, 0, -arm], [-arm, 0, arm, 0], [k_m, -k_m, k_m, -k_m]], dtype=state.dtype)
    f = torch.linalg.solve(Mx, torch.stack([T, tau[:, 0], tau[:, 1], tau[:, 2]], 1).T).T
    return torch.clamp(f, 0.0, 4.0 * mass * g / 4 * 2.5)
