"""The state loss and the three rendering-gradient regularizers (paper Eq. 10 and Eq. 12).

Notation (docs/training.md §Losses).  For one image b: x_b is the normalized network input, the K stored
derivative images carried through the input normalization are the tangents X_bj = ∂x_b/∂ψ_j
(:meth:`risp_train.normalization.Normalization.tangents`), N is the network, ŷ_b = N(x_b) its normalized
prediction and y_b the normalized target (T values).  The rendering-gradient matrix of image b is

    M_b = ∂N(x_b)/∂ψ = (∂N/∂x)(x_b) · [X_b1 … X_bK]                      (T × K)

* state error        ℓ_b = (1/T) Σ_t |ŷ_bt − y_bt|                               (L1)
* ``exact``          r_b = ‖M_b‖_F                                            (paper Eq. 10)
  K forward-mode products (∂N/∂x)·X_bj, one per ψ_j, batched over the K tangents (``torch.func.vmap``
  over ``torch.func.jvp``, or the equivalent explicit tangent rules of forward_tangents.py):
  O(K·|θ|) instead of the paper's O(T·|θ|) rows of ∂N/∂x.
* ``stochastic``     r_b = ‖M_b v_b‖₂²,  v_b ~ N(0, I_K)                          (one JVP along X_b v_b)
  Unbiased for the *squared* Frobenius norm, E r_b = ‖M_b‖_F², with variance
  Var r_b = 2‖M_bᵀM_b‖_F² = 2 Σ_i σ_i⁴ ≤ 2‖M_b‖_F⁴ (σ_i the singular values of M_b), i.e. a relative
  standard deviation between √(2/K) (all σ_i equal) and √2 (rank one) per image, reduced by √B over
  the batch.  Its gradient is unbiased for ∇‖M_b‖_F².  Because ∇‖M‖_F² = 2‖M‖_F ∇‖M‖_F, a weight γ_s
  on the squared form matches γ on the exact (non-squared) form where ‖M_b‖_F ≈ γ/(2γ_s); we use the
  same γ for both (the squared form penalises large derivatives more and small ones less).
* ``surrogate``      r_b = ‖∂ℓ_b/∂ψ‖₂ = ‖Σ_pixels (∂ℓ_b/∂x_b) ⊙ X_bj‖₂ over j      (paper Eq. 12)
  One double backward: the gradient of the state error w.r.t. the image, built with
  ``create_graph=True``, contracted with the stored tangents.

Images are independent under instance normalization, so ∂(Σ_b ℓ_b)/∂x_b = ∂ℓ_b/∂x_b and the per-image
quantities are exact.

**One scale for the three forms** (issue 8, docs/training.md §Calibrated regularizer).  The raw forms above
live on different scales (‖M‖_F, ‖M‖_F², ≈‖M‖_F/T) and ψ's components on different ranges.  The loss
uses them calibrated to one quantity with a meaning: the first-order *rendering-induced error*

    R = E_ψ' [(1/T) Σ_t |ŷ_t(ψ') − ŷ_t(ψ)|] ≈ √(2/π) · ‖M̃‖_F / √T,     M̃ = M · diag(σ_ψ)

i.e. the L1 distance (in the state error's own units) by which the prediction moves when the rendering
parameters are redrawn from the training distribution (σ_ψj = (high_j − low_j)/√12, the standard
deviation of the uniform ψ_j; for shards of the target domain, whose colours are drawn from two intervals, that
mixture's standard deviation: ``psi_scale``; Gaussian approximation of E|·|).  Per batch, with c_T = √(2/π)/√T and the
tangents scaled by σ_ψ:

* ``exact``       R = c_T · (1/B) Σ_b ‖M̃_b‖_F
* ``stochastic``  R = c_T · √((1/B) Σ_b ‖M̃_b v_b‖²)   (the square root of the batch-mean estimate of
  ‖M̃‖_F²: consistent for the batch's RMS of ‖M̃_b‖_F, which is ≥ and close to its mean)
* ``surrogate``   R = √(2/π) · √T · (1/B) Σ_b ‖∂ℓ_b/∂ψ̃‖   (T ∂ℓ_b/∂ψ̃ = M̃_bᵀ sign(ŷ_b − y_b), whose norm
  has squared norm ‖M̃_b‖_F² in expectation over sign patterns independent of M̃_b)

and L = (1/B) Σ_b ℓ_b + γ R with a dimensionless γ: γ = 1 weighs the rendering-induced error like the state
error itself (γ = 0 for ``none``).  No factor depends on the preset; the per-environment default γ comes
from a sweep (risp_train/config.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn
from torch.func import jvp, vmap

REGULARIZERS = ("none", "surrogate", "exact", "stochastic")
SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)  # E|z| for z ~ N(0, 1)


def state_error(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """ℓ_b = mean_t |ŷ_bt − y_bt| for pred, target (B, T) → (B,)."""
    return (pred - target).abs().mean(dim=-1)


ENGINES = ("auto", "explicit", "functorch")


def rendering_gradients_functorch(net: nn.Module, x: torch.Tensor,
                                  tangents: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(ŷ, M) by ``torch.func.jvp`` vmapped over the K tangents (any network; the reference engine)."""

    def one_direction(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return jvp(net, (x,), (t,))

    # the primal does not depend on the tangent: vmap returns it expanded along K (a view, no copy)
    primal, tangent_out = vmap(one_direction, in_dims=1, out_dims=(0, 1))(tangents)  # (K, B, T), (B, K, T)
    return primal[0], tangent_out


def rendering_gradients(net: nn.Module, x: torch.Tensor, tangents: torch.Tensor,
                        engine: str = "auto") -> tuple[torch.Tensor, torch.Tensor]:
    """(ŷ, M): ŷ = N(x) (B, T) and M_b = (∂N/∂x)(x_b)·X_b stacked as (B, K, T).

    x (B, C, H, W), tangents X (B, K, C, H, W).  Forward-mode products, both outputs on the autograd tape
    so the loss can be backpropagated to the parameters.  Engines (identical values, tested):
    ``explicit`` propagates the K tangents as one batch through hand-written tangent rules of the
    ResNet's layers (:mod:`risp_train.forward_tangents`, faster); ``functorch`` vmaps ``torch.func.jvp``
    over the K tangents and works for any network; ``auto`` picks ``explicit`` for :class:`ResNet18`.
    """
    from .forward_tangents import forward_with_tangents
    from .model import ResNet18

    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; choose one of {ENGINES}")
    if engine == "explicit" or (engine == "auto" and isinstance(net, ResNet18)):
        return forward_with_tangents(net, x, tangents)
    return rendering_gradients_functorch(net, x, tangents)


def exact_regularizer(net: nn.Module, x: torch.Tensor, tangents: torch.Tensor,
                      engine: str = "auto") -> tuple[torch.Tensor, torch.Tensor]:
    """(ŷ, r) with r_b = ‖M_b‖_F (paper Eq. 10), r (B,)."""
    pred, m = rendering_gradients(net, x, tangents, engine)
    return pred, torch.linalg.vector_norm(m.flatten(1), dim=1)


def stochastic_regularizer(net: nn.Module, x: torch.Tensor, tangents: torch.Tensor, v: torch.Tensor,
                           engine: str = "auto") -> tuple[torch.Tensor, torch.Tensor]:
    """(ŷ, r) with r_b = ‖(∂N/∂x)(x_b)·(X_b v_b)‖² for v (B, K) ~ N(0, I_K): E r_b = ‖M_b‖_F²."""
    direction = torch.einsum("bk,bkchw->bchw", v.to(tangents.dtype), tangents)  # X_b v_b, (B, C, H, W)
    pred, m = rendering_gradients(net, x, direction.unsqueeze(1), engine)  # one JVP; m (B, 1, T)
    return pred, (m[:, 0] * m[:, 0]).sum(dim=1)


def surrogate_regularizer(
    net: nn.Module, x: torch.Tensor, tangents: torch.Tensor, target: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(ŷ, ℓ, r) with r_b = ‖∂ℓ_b/∂ψ‖₂ (paper Eq. 12), by double backward through ∂ℓ/∂x."""
    with torch.enable_grad():  # the inner gradient is needed even when the caller evaluates under no_grad
        if not x.requires_grad:
            x = x.detach().requires_grad_(True)
        pred = net(x)
        err = state_error(pred, target)  # (B,)
        (g,) = torch.autograd.grad(err.sum(), x, create_graph=True)  # ∂ℓ_b/∂x_b, (B, C, H, W)
    dl_dpsi = torch.einsum("bchw,bkchw->bk", g, tangents)  # (B, K)
    return pred, err, torch.linalg.vector_norm(dl_dpsi, dim=1)


def psi_scale(env: str, domain: str = "train") -> torch.Tensor:
    """σ_ψ (K,) float64: the standard deviation of each ψ_j of ``env`` as ``domain`` samples it (the shards'
    manifest says which).  One interval [a, b] (every train-domain ψ_j): (b − a)/√12.  Several intervals, one
    chosen uniformly and ψ_j uniform in it (target-domain colours, risp_data.psi.sample_rendering): the
    mixture's σ² = mean_i((b_i − a_i)²/12 + m_i²) − (mean_i m_i)², m_i = (a_i + b_i)/2."""
    from risp_data.psi import psi_specs

    def sigma(spec) -> float:
        if len(spec.intervals) <= 1:
            return (spec.high - spec.low) / math.sqrt(12.0)
        mids = [(a + b) / 2 for a, b in spec.intervals]
        second = sum((b - a) ** 2 / 12 + m * m for (a, b), m in zip(spec.intervals, mids)) / len(mids)
        return math.sqrt(second - (sum(mids) / len(mids)) ** 2)

    return torch.tensor([sigma(s) for s in psi_specs(env, domain)], dtype=torch.float64)


def calibrated_regularizer(net: nn.Module, x: torch.Tensor, target: torch.Tensor, reg: str, tangents: torch.Tensor,
                           v: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(ℓ (B,), R scalar): the state errors and the batch's rendering-induced error R of form ``reg``
    (module docstring §One scale).  ``tangents`` are ∂x/∂ψ̃, i.e. already multiplied by σ_ψ."""
    T = target.shape[-1]
    c_t = SQRT_2_OVER_PI / math.sqrt(T)
    if reg == "exact":
        pred, r = exact_regularizer(net, x, tangents)
        return state_error(pred, target), c_t * r.mean()
    if reg == "stochastic":
        pred, r = stochastic_regularizer(net, x, tangents, v)
        return state_error(pred, target), c_t * torch.sqrt(r.mean() + 1e-20)  # tiny floor: finite gradient at 0
    if reg == "surrogate":
        _, err, r = surrogate_regularizer(net, x, tangents, target)
        return err, SQRT_2_OVER_PI * math.sqrt(T) * r.mean()
    raise ValueError(f"unknown regularizer {reg!r}; choose one of {REGULARIZERS}")


@dataclass(frozen=True)
class LossTerms:
    total: torch.Tensor  # scalar, differentiable
    error: torch.Tensor  # scalar, mean_b ℓ_b (detached)
    reg: torch.Tensor  # scalar, the calibrated rendering-induced error R (detached; 0 for "none")


def risp_loss(
    net: nn.Module,
    x: torch.Tensor,
    target: torch.Tensor,
    reg: str,
    gamma: float,
    tangents: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    psi_scale: torch.Tensor | None = None,
) -> LossTerms:
    """L = mean_b ℓ_b + γ R for regularizer ``reg`` (one of :data:`REGULARIZERS`; R calibrated, module docstring).

    ``tangents`` (B, K, C, H, W) = ∂x/∂ψ is required unless reg is ``none``; ``psi_scale`` σ_ψ (K,) turns
    them into ∂x/∂ψ̃ (None: ψ taken as already standardized); ``generator`` draws v for ``stochastic``
    (explicit, so that a resumed run draws the same v).
    """
    if reg not in REGULARIZERS:
        raise ValueError(f"unknown regularizer {reg!r}; choose one of {REGULARIZERS}")
    if reg == "none":
        err = state_error(net(x), target)
        return LossTerms(err.mean(), err.mean().detach(), torch.zeros((), dtype=err.dtype))
    if tangents is None:
        raise ValueError(f"regularizer {reg!r} needs the rendering Jacobians")
    if psi_scale is not None:
        tangents = tangents * psi_scale.to(tangents).view(1, -1, 1, 1, 1)
    v = None
    if reg == "stochastic":
        if generator is None:
            raise ValueError("the stochastic regularizer needs an explicit torch.Generator")
        v = torch.randn(x.shape[0], tangents.shape[1], generator=generator, dtype=x.dtype, device="cpu").to(x.device)
    err, r = calibrated_regularizer(net, x, target, reg, tangents, v)
    total = err.mean() + gamma * r
    return LossTerms(total, err.mean().detach(), r.detach())


def gamma_at(step: int, total_steps: int, gamma: float, ramp_fraction: float, start_fraction: float = 0.0) -> float:
    """γ(step): 0 before the start s = start_fraction · total_steps, then a linear ramp to γ over ramp_fraction of
    the steps that follow the start, (total_steps − s) · ramp_fraction, constant afterwards.  A late start lets
    the state error shape the features first: at initialization R's parameter gradient is 25–100× the state
    error's (benchmarks/reg_gradient_ratio.py)."""
    start = start_fraction * total_steps
    if step < start:
        return 0.0
    ramp = ramp_fraction * (total_steps - start)
    if ramp <= 0:
        return gamma
    return gamma * min(1.0, (step - start) / ramp)
