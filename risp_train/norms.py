"""Instance normalization without affine parameters, written out so that its second derivatives are exact.

``torch.nn.InstanceNorm2d`` returns wrong second-order gradients in torch 2.13 (the parameter gradient of
the RISP regularizer ‖∂N/∂I·J‖ was off by 3–7 % against central differences; ../shared/NOTES.md).  The
same function built from elementary ops (mean, centred second moment, rsqrt) differentiates correctly
in reverse mode, forward mode (``torch.func.jvp``) and in any composition of the two, and it batches
under ``torch.func.vmap``.  tests/test_train_regularizers.py checks the whole regularizer against
finite differences, because ``gradgradcheck`` on the op alone does not reveal the bug.
"""

from __future__ import annotations

import torch
from torch import nn


def instance_norm(x: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    """y = (x − μ) / sqrt(σ² + ε) with μ, σ² (biased) over the spatial axes of each sample and channel.

    x: (B, C, H, W).  Identical forward values to ``F.instance_norm(x, eps=eps)`` without running stats.
    """
    mean = x.mean(dim=(-2, -1), keepdim=True)
    centred = x - mean
    var = (centred * centred).mean(dim=(-2, -1), keepdim=True)
    return centred * torch.rsqrt(var + eps)


class InstanceNorm(nn.Module):
    """Module wrapper of :func:`instance_norm` (no affine parameters, no running statistics)."""

    def __init__(self, eps: float = 1e-5):
        super().__init__()
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return instance_norm(x, self.eps)

    def extra_repr(self) -> str:
        return f"eps={self.eps}"
