"""Input and target normalization, and the chain rule that carries the stored J through it.

Images.  A raw image I (linear RGB, ≥ 0, unbounded highlights) enters the network as

    x_c = (log1p(max(I_c, 0)) − m_c) / s_c                                      (c = R, G, B)

with per-channel mean m_c and standard deviation s_c of log1p(I_c) over the pixels of the statistics
samples.  log1p compresses highlights while staying linear (≈ I) in the dark.  The stored derivative
images are w.r.t. the *raw* image, J_j = ∂I/∂ψ_j, so the regularizers use the tangent of x:

    ∂x_c/∂ψ_j = [I_c > 0] / ((1 + I_c) s_c) · J_j,c                            (elementwise)

Targets.  The network predicts the normalized target ŷ = (y − μ) / σ with y = env.state_to_target(s)
and per-dimension mean μ and standard deviation σ (floored at 1e-3) over the statistics samples.

Both sets of statistics are computed by one streamed pass over the first ``stats_samples`` training
samples (default 256) and stored in the checkpoint.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

STD_FLOOR = 1e-6  # image channels
TARGET_STD_FLOOR = 1e-3  # a (nearly) constant target dimension must not blow up its normalized error


@dataclass(frozen=True)
class Normalization:
    image_mean: tuple[float, float, float]  # m_c of log1p(I_c)
    image_std: tuple[float, float, float]  # s_c
    target_mean: tuple[float, ...]  # μ
    target_std: tuple[float, ...]  # σ

    # -- images -----------------------------------------------------------------------------------------
    def _img_stats(self, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        m = torch.tensor(self.image_mean, dtype=ref.dtype, device=ref.device).view(3, 1, 1)
        s = torch.tensor(self.image_std, dtype=ref.dtype, device=ref.device).view(3, 1, 1)
        return m, s

    def images(self, image: torch.Tensor) -> torch.Tensor:
        """Raw (B, H, W, 3) → normalized network input x (B, 3, H, W)."""
        m, s = self._img_stats(image)
        # contiguous NCHW, not the channels-last strides of the permute: see risp_train.model.as_nchw
        return ((torch.log1p(image.clamp_min(0)).permute(0, 3, 1, 2) - m) / s).contiguous()

    def tangents(self, image: torch.Tensor, jacobian: torch.Tensor) -> torch.Tensor:
        """Chain rule: raw J (B, K, H, W, 3) at raw image (B, H, W, 3) → ∂x/∂ψ (B, K, 3, H, W)."""
        _, s = self._img_stats(image)
        # d log1p(max(I,0)) / dI = [I > 0] / (1 + I)
        dlog = torch.where(image > 0, 1.0 / (1.0 + image.clamp_min(0)), torch.zeros_like(image))
        dx = (dlog.unsqueeze(1) * jacobian).permute(0, 1, 4, 2, 3)  # (B, K, 3, H, W)
        return (dx / s).contiguous()

    # -- targets ----------------------------------------------------------------------------------------
    def _tgt_stats(self, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu = torch.tensor(self.target_mean, dtype=ref.dtype, device=ref.device)
        sd = torch.tensor(self.target_std, dtype=ref.dtype, device=ref.device)
        return mu, sd

    def targets(self, target: torch.Tensor) -> torch.Tensor:
        """Raw target y (B, T) → normalized ŷ."""
        mu, sd = self._tgt_stats(target)
        return (target - mu) / sd

    def untargets(self, normalized: torch.Tensor) -> torch.Tensor:
        """Normalized ŷ (B, T) → raw target y."""
        mu, sd = self._tgt_stats(normalized)
        return normalized * sd + mu

    # -- storage ----------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {k: list(getattr(self, k)) for k in ("image_mean", "image_std", "target_mean", "target_std")}

    @staticmethod
    def from_dict(d: dict) -> "Normalization":
        return Normalization(**{k: tuple(float(v) for v in d[k]) for k in
                                ("image_mean", "image_std", "target_mean", "target_std")})


class StatsAccumulator:
    """Streamed sums for :class:`Normalization` (float64 sums; no sample is kept)."""

    def __init__(self, target_dim: int):
        self.n_pix = 0
        self.s1 = torch.zeros(3, dtype=torch.float64)
        self.s2 = torch.zeros(3, dtype=torch.float64)
        self.n = 0
        self.t1 = torch.zeros(target_dim, dtype=torch.float64)
        self.t2 = torch.zeros(target_dim, dtype=torch.float64)

    def add(self, image: torch.Tensor, target: torch.Tensor) -> None:
        """image (B, H, W, 3) raw, target (B, T) raw."""
        li = torch.log1p(image.double().clamp_min(0)).reshape(-1, 3)
        self.n_pix += li.shape[0]
        self.s1 += li.sum(0)
        self.s2 += (li * li).sum(0)
        t = target.double().reshape(-1, self.t1.numel())
        self.n += t.shape[0]
        self.t1 += t.sum(0)
        self.t2 += (t * t).sum(0)

    def result(self) -> Normalization:
        if self.n == 0:
            raise ValueError("no samples for normalization statistics")
        m = self.s1 / self.n_pix
        s = (self.s2 / self.n_pix - m * m).clamp_min(0).sqrt().clamp_min(STD_FLOOR)
        mu = self.t1 / self.n
        sd = (self.t2 / self.n - mu * mu).clamp_min(0).sqrt().clamp_min(TARGET_STD_FLOOR)
        return Normalization(tuple(m.tolist()), tuple(s.tolist()), tuple(mu.tolist()), tuple(sd.tolist()))
