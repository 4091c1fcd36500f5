"""Forward-mode products of the network with K tangents at once, written out layer by layer.

``forward_with_tangents(net, x, X)`` returns N(x) and (∂N/∂x)(x)·X_j for all j — the same numbers as
``vmap(jvp(net))`` (regularizers.rendering_gradients_functorch, compared in the tests to 1e-10 in
float64) — but propagates the K tangents as one contiguous (K·B)-image batch through every linear layer
(convolutions, pooling, the head) and applies each nonlinearity's derivative at the primal point by
broadcasting.  That keeps the exact regularizer near its arithmetic floor of (1 + K) plain passes;
functorch's batched forward mode spends extra time on strided elementwise kernels
(docs/training.md §Losses; benchmarks/bench_train.py).  Every formula below is ordinary autograd-
differentiable torch code, so the weight gradient of any function of the tangents is exact.

Tangent rules (primal x, tangent ẋ; statistics over the spatial axes):
    conv / linear (no bias on the tangent)   ẏ = W ∗ ẋ
    instance norm  y = (x − μ)/√(σ² + ε)      ẏ = (ċ − y · mean(y ⊙ ċ)) / √(σ² + ε),  ċ = ẋ − mean(ẋ)
    SiLU           y = x σ(x)                 ẏ = σ(x) (1 + x (1 − σ(x))) ⊙ ẋ
    max-pool                                  ẏ = ẋ at the primal's arg-max
    average pool                              ẏ = mean(ẋ)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .model import BasicBlock, ResNet18, as_nchw
from .norms import InstanceNorm

Pair = tuple[torch.Tensor, torch.Tensor]  # primal (B, C, H, W), tangents (K, B, C, H, W)


def _conv(m: nn.Conv2d, x: torch.Tensor, xd: torch.Tensor) -> Pair:
    k, b = xd.shape[:2]
    y = m(x)
    yd = F.conv2d(xd.flatten(0, 1), m.weight, None, m.stride, m.padding, m.dilation, m.groups)
    return y, yd.unflatten(0, (k, b))


def _instance_norm(m: InstanceNorm, x: torch.Tensor, xd: torch.Tensor) -> Pair:
    mean = x.mean(dim=(-2, -1), keepdim=True)
    c = x - mean
    inv = torch.rsqrt((c * c).mean(dim=(-2, -1), keepdim=True) + m.eps)
    y = c * inv
    cd = xd - xd.mean(dim=(-2, -1), keepdim=True)
    yd = (cd - y * (y * cd).mean(dim=(-2, -1), keepdim=True)) * inv
    return y, yd


def _silu(x: torch.Tensor, xd: torch.Tensor) -> Pair:
    s = torch.sigmoid(x)
    y = x * s
    return y, (s * (1 + x * (1 - s))) * xd


def _max_pool(m: nn.MaxPool2d, x: torch.Tensor, xd: torch.Tensor) -> Pair:
    y, idx = F.max_pool2d(x, m.kernel_size, m.stride, m.padding, m.dilation, m.ceil_mode, return_indices=True)
    k = xd.shape[0]
    flat_idx = idx.flatten(-2).unsqueeze(0).expand(k, *idx.shape[:-2], -1)  # (K, B, C, h·w)
    yd = xd.flatten(-2).gather(-1, flat_idx).view(k, *y.shape)
    return y, yd


def _block(m: BasicBlock, x: torch.Tensor, xd: torch.Tensor) -> Pair:
    h, hd = _silu(*_instance_norm(m.norm1, *_conv(m.conv1, x, xd)))
    h, hd = _instance_norm(m.norm2, *_conv(m.conv2, h, hd))
    s, sd = _module(m.shortcut, x, xd)
    return _silu(h + s, hd + sd)


def _module(m: nn.Module, x: torch.Tensor, xd: torch.Tensor) -> Pair:
    if isinstance(m, nn.Sequential):
        for child in m:
            x, xd = _module(child, x, xd)
        return x, xd
    if isinstance(m, nn.Conv2d):
        return _conv(m, x, xd)
    if isinstance(m, InstanceNorm):
        return _instance_norm(m, x, xd)
    if isinstance(m, nn.SiLU):
        return _silu(x, xd)
    if isinstance(m, nn.MaxPool2d):
        return _max_pool(m, x, xd)
    if isinstance(m, BasicBlock):
        return _block(m, x, xd)
    if isinstance(m, nn.Identity):
        return x, xd
    raise TypeError(f"no tangent rule for {type(m).__name__}")


def forward_with_tangents(net: ResNet18, x: torch.Tensor, tangents: torch.Tensor) -> Pair:
    """(ŷ (B, T), M (B, K, T)): N(x) and (∂N/∂x)(x)·X_j for x (B, C, H, W), tangents X (B, K, C, H, W)."""
    xd = tangents.transpose(0, 1)  # (K, B, C, H, W): tangent index first, so the batch of K·B is contiguous
    h, hd = _module(net.stages, *_module(net.stem, as_nchw(x), as_nchw(xd)))  # NCHW: see model.as_nchw
    if h.shape[-1] * h.shape[-2] == 1:
        raise ValueError("input too small: the last stage is 1×1, where instance norm is identically zero")
    pooled, pooled_d = h.mean(dim=(-2, -1)), hd.mean(dim=(-2, -1))  # (B, 8w), (K, B, 8w)
    y = net.head(pooled)
    yd = pooled_d @ net.head.weight.T  # (K, B, T)
    return y, yd.transpose(0, 1)
