"""Does a model's held-out residual still depend on a regressor? (docs/diagnose.md §6, "no confident wrong names")

A constant force fitted to data whose real cause depends on height (ground effect) lowers the RSS a lot and
can reach the noise floor on average, yet its residual still varies systematically with height.  Before a
cause is named, the selected model's held-out residuals are tested against every candidate regressor:

* residual: the normalised open-loop error e/σ of each rate channel (velocity, angular velocity; hand/rod:
  every rate) H samples after **every** held-out sample (stride 1, at most MAX_SEGMENTS, a seeded subset) —
  an unmodelled acceleration integrates over the H samples, measurement noise does not; the residuals of
  starts i and i+1 share no measured sample, so their noise is nearly independent;
* regressor: its value at the segment start (speed, height, tilt, thrust, contact, time, …);
* test: the segments are put in B quantile bins of the regressor (B = 6, fewer so that every bin holds at
  least MIN_PER_BIN); Kruskal–Wallis rank test across the bins (B − 1 degrees of freedom) — ranks, because
  contact residuals are heavy-tailed (a mean-based Welch test flagged the true model on synthetic cube
  tosses); effect size ε² = H / (n − 1) (reported as ``eta2``);
* a dependence is declared when the Bonferroni-corrected p-value (× regressors × channels) is below
  ALPHA = 1e-3 **and** the rank effect size ε² is at least ETA2_MIN = 0.15 — with thousands of segments a statistically detectable but tiny trend is no
  reason to withhold a name.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.stats import kruskal

from risp_data.errors import RispError

from .fit import make_segments, predict
from .residuals import _rate_channels, regressors

BINS = 6
ALPHA = 1e-3
ETA2_MIN = 0.15
MIN_PER_BIN = 15
MAX_SEGMENTS = 2000


@dataclass
class Dependence:
    regressor: str
    channel: str
    p_value: float  # Bonferroni-corrected
    eta2: float
    bin_centres: list[float]
    bin_means: list[float]  # in units of σ of the channel

    @property
    def significant(self) -> bool:
        return self.p_value < ALPHA and self.eta2 >= ETA2_MIN

    def as_dict(self) -> dict:
        return {"regressor": self.regressor, "channel": self.channel, "p_value": self.p_value, "eta2": self.eta2,
                "bin_centres": self.bin_centres, "bin_means_sigma": self.bin_means, "significant": self.significant}


def _anova(x: np.ndarray, y: np.ndarray) -> tuple[float, float, list[float], list[float], int] | None:
    """(p-value, ε², bin centres, bin means, dof) of y binned by quantiles of x: Kruskal–Wallis rank test
    (robust to the heavy tails of contact residuals), ε² = H / (n − 1) its rank effect size; None if x does
    not vary."""
    bins = min(BINS, len(x) // MIN_PER_BIN)
    if bins < 2:
        return None
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    if len(edges) < 2:
        return None
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    used = [b for b in range(len(edges) - 1) if (idx == b).sum() >= 3]
    if len(used) < 2 or np.ptp(y) == 0:
        return None
    H, p = kruskal(*[y[idx == b] for b in used])
    centres = [float(x[idx == b].mean()) for b in used]
    means = [float(y[idx == b].mean()) for b in used]
    return float(p), float(H) / max(len(y) - 1, 1), centres, means, len(used) - 1


def residual_dependence(fit, obs, sigma, trajs, horizon: int, k: int, seed: int, phi: float = 0.0) -> list[Dependence]:
    """Every (regressor, rate channel) test, most significant first (see the module docstring).

    With time-correlated (filtered) noise of lag-1 correlation φ the segment starts are spaced by the
    samples it takes the correlation to fall below 0.1 (ln 0.1 / ln φ), so the tested residuals stay
    nearly independent; fewer segments mean a weaker test, never a falsely significant one."""
    if trajs[0].pos is None:
        # validated on rigid bodies (quadrotor, cube) only: on the rod's synthetic data it flagged the true
        # model (ρ = 1.00) against |command| in one of its many node channels — not used for hand and rod
        return []
    sim = fit.model.sim
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 3]))
    stride = 1 if phi <= 0 else max(1, int(np.ceil(np.log(0.1) / np.log(min(phi, 0.999)))))
    try:
        seg = make_segments(sim, trajs, horizon, k, stride=stride, max_segments=MAX_SEGMENTS, rng=rng,
                            params=fit.model.base)
    except RispError:
        return []
    with torch.no_grad():
        pred = predict(sim, fit.params, seg)
        e = (obs.error(pred[:, -1], seg.meas[:, -1]) / sigma).numpy()  # (S, C)
    regs = {k: v for k, v in regressors(sim, trajs, seg).items() if np.ptp(v) > 0}
    chans = _rate_channels(obs)
    tests = []
    for name, x in regs.items():
        for c in chans:
            res = _anova(x, e[:, c])
            if res is None:
                continue
            p, eta2, centres, means, dof = res
            tests.append((name, c, p, eta2, centres, means))
    m = max(len(tests), 1)
    out = [Dependence(name, obs.channels[c], min(1.0, p * m), eta2, centres, means)
           for name, c, p, eta2, centres, means in tests]
    return sorted(out, key=lambda d: (not d.significant, d.p_value, -d.eta2))
