"""``risp-task estimate``: per-frame states of a video.

With the default ``--iterations 0`` the estimate is the network's prediction N(I_t) (the paper's state
estimation).  With iterations > 0 the per-frame states are refined by the shared loop under the chosen loss
(``render``: analysis by synthesis, N(R(s_t)) → N(I_t); ``oracle``: towards the truth, for evaluation).
"""

from __future__ import annotations

import torch

from .context import Context
from .loop import Problem


def build(ctx: Context) -> Problem:
    init = ctx.predicted.detach().clone().to(torch.float64)
    if ctx.cfg.init == "random":
        low = torch.tensor(ctx.env.state_low, dtype=torch.float64)
        high = torch.tensor(ctx.env.state_high, dtype=torch.float64)
        init = low + (high - low) * torch.from_numpy(ctx.rng.random(init.shape))
    states = init.requires_grad_(True)

    def estimates():
        return {"env_states": states.detach().tolist(), "frames": ctx.keep}

    return Problem(variables={"states": states}, states=lambda: states, estimates=estimates,
                   frames=list(range(len(ctx.keep))))
