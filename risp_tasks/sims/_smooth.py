"""Smooth stand-ins for clamps and one-sided limits, shared by the hand and rod simulators.

A hard clamp has zero gradient wherever it binds (docs/models/hand.md, "Torque schedule"); these
C∞ versions keep a gradient everywhere and equal the hard versions up to an error that decays
exponentially with the distance from the corner (at the corner itself the error is ``width · log 2``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def softplus_width(x: torch.Tensor, width: float) -> torch.Tensor:
    """``width · log(1 + exp(x / width))``: a ramp max(x, 0) whose corner is rounded over ``width``.

    ``threshold`` is raised far above the default so the function stays analytic in float64 gradient
    checks (PyTorch switches to the identity beyond ``threshold``).
    """
    return F.softplus(x, beta=1.0 / width, threshold=60.0)


def smooth_clamp(x: torch.Tensor, low: float, high: float, width: float) -> torch.Tensor:
    """``low + sp(x − low) − sp(x − high)`` with ``sp = softplus_width(·, width)``.

    Equals ``clamp(x, low, high)`` up to ``width · log 2`` at the two corners and exponentially
    closer away from them; ``width = 0`` gives the hard clamp.
    """
    if width <= 0:
        return x.clamp(low, high)
    return low + softplus_width(x - low, width) - softplus_width(x - high, width)
