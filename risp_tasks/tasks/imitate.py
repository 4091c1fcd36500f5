"""``risp-task imitate``: the action sequence that reproduces a video's motion (paper Sec. 5.4/5.5).

Actions are one row per source frame (held over the frame's k simulator steps), optimised in normalised
coordinates u = centre + scale·x (centre: hover for the quadrotor, 0 otherwise; scale: ACTION_SCALE).
Initialisation (``--init``): ``default`` x = 0; ``random`` x ~ U(−1, 1) (seeded); ``track`` (quadrotor) a
geometric tracking controller (Lee et al. 2010) flown in the simulator along the network-estimated
trajectory, whose per-frame thrusts start the refinement (paper Sec. 5.5).  Physical parameters are the
simulator's nominal ones; the initial state comes from the first two frames' estimates.
"""

from __future__ import annotations

import torch

from risp_data.errors import RispError

from .context import Context
from .loop import Problem
from .simulate import ACTION_SCALE, action_centre, frame_states, initial_sim_state, to_file_actions


def initial_actions(ctx: Context, params: torch.Tensor, s0: torch.Tensor, n_frames: int) -> torch.Tensor:
    """x0 (n_frames, A) in normalised coordinates."""
    sim, A = ctx.sim, ctx.sim.action_dim
    if ctx.cfg.init == "random":
        return torch.from_numpy(ctx.rng.uniform(-1, 1, (n_frames, A)))
    if ctx.cfg.init == "track":
        if sim.env != "quadrotor":
            raise RispError("--init track is for the quadrotor (a tracking controller)")
        u = track(ctx, params, s0, n_frames)
        return (u - action_centre(sim, params)) / ACTION_SCALE[sim.env]
    return torch.zeros(n_frames, A, dtype=torch.float64)


def track(ctx: Context, params: torch.Tensor, s0: torch.Tensor, n_frames: int) -> torch.Tensor:
    """Commands (n_frames, 4) of a tracking controller that follows the estimated positions."""
    import numpy as np

    from risp_data.envs.quadrotor import ARM_LENGTH

    from ..diagnose.synth import _quad_controller

    sim = ctx.sim
    t_keep = np.asarray(ctx.keep, np.float64)
    pos = ctx.predicted[:, :3].detach().numpy()
    t = np.arange(n_frames, dtype=np.float64)
    ref_p = torch.tensor(np.stack([np.interp(t, t_keep, pos[:, i]) for i in range(3)], 1))
    ref_v = torch.tensor(np.gradient(ref_p.numpy(), axis=0) * ctx.fps)
    mass = float(params[0, sim.param_index("mass")])
    inertia = params[0, [sim.param_index(n) for n in ("Ixx", "Iyy", "Izz")]]
    k_m, k_f = float(params[0, sim.param_index("k_m")]), float(params[0, sim.param_index("k_f")])
    s, out = s0.clone(), []
    with torch.no_grad():
        for i in range(n_frames):
            u = _quad_controller(s, ref_p[i:i + 1], ref_v[i:i + 1], mass, inertia, k_m, ARM_LENGTH) / k_f
            out.append(u[0])
            for j in range(ctx.k):
                s = sim.step(params, s, u, i * ctx.k + j)
    return torch.stack(out)


def build(ctx: Context, n_frames: int | None = None, s0: torch.Tensor | None = None) -> Problem:
    sim = ctx.sim
    if sim.action_dim == 0:
        raise RispError(f"the {sim.env} has no actions to imitate; imitate works for: quadrotor, hand, rod")
    n_frames = ctx.n_source if n_frames is None else n_frames
    params = sim.default_params()
    if s0 is None:
        second = ctx.predicted[1] if len(ctx.keep) > 1 else None
        fps = ctx.fps / (ctx.keep[1] - ctx.keep[0]) if len(ctx.keep) > 1 else ctx.fps
        s0 = initial_sim_state(sim, ctx.predicted[0], second, fps)
    centre, scale = action_centre(sim, params), ACTION_SCALE[sim.env]
    x0 = initial_actions(ctx, params, s0, n_frames)
    x = x0.clone().requires_grad_(True)

    def actions(v):
        return centre + scale * v

    def estimates():
        return {"actions": to_file_actions(sim, params, actions(x.detach())).tolist(),
                "initial_actions": to_file_actions(sim, params, actions(x0)).tolist()}

    return Problem(variables={"actions": x}, states=lambda: frame_states(sim, params, s0, actions(x), n_frames, ctx.k),
                   estimates=estimates, info={"initial_state": s0[0].tolist()})
