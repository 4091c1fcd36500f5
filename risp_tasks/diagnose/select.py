"""Scoring candidate models on held-out data and naming the cause (docs/diagnose.md §6 Scores and the decision).

Score (held-out BIC).  With e the robust normalised held-out multiple-shooting residuals of a fitted
model (:func:`fit.robust`), RSS = Σe², n = S·H·C residuals, n_eff = S·C (segments × channels: errors along one segment's horizon are
strongly correlated, segments are not overlapping and nearly independent) and k free parameters:

    BIC = n_eff · ln(RSS / n) + k · ln(n_eff)

ΔBIC = BIC_base − BIC_model > 0 favours the model.

Decision.
* A candidate *beats the base clearly* when ΔBIC ≥ :data:`DELTA_BIC_MIN` (10: "very strong" on the
  Kass–Raftery scale) **and** it lowers the held-out RSS by at least :data:`MIN_RSS_REDUCTION` (5 %).
  A pair replaces its best single only if it beats that single by the same margins.
* Noise floor: the held-out RSS expected if the model were exact is measured by a parametric bootstrap
  (:func:`noise_floor`): measurement noise of the estimated level is added to states simulated by the
  fitted model from the measured start states, and the same residuals are computed.  ρ = RSS / RSS_noise.
* cause = the selected candidate when it beats the base and leaves ρ ≤ :data:`RHO_MAX` (1.5);
  ``none`` when no candidate beats the base and the base leaves ρ ≤ RHO_MAX;
  ``unexplained`` when the best model (base or candidate) still leaves ρ > RHO_MAX — a significant
  residual that no candidate accounts for.  Never a name when the residual remains significant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .adapter import Observer, consistent_start
from .fit import DTYPE, FitResult, Segments, predict, robust
from ..sims._rigid import GRAVITY

DELTA_BIC_MIN = 10.0
MIN_RSS_REDUCTION = 0.05
RHO_MAX = 1.5
BOOTSTRAP_REPLICAS = 2


@dataclass
class Score:
    name: str
    effects: tuple[str, ...]
    k: int
    rss: float
    n: int
    n_eff: int
    bic: float
    rho: float = float("nan")
    noise_rss: float = float("nan")

    def delta_bic(self, ref: "Score") -> float:
        return ref.bic - self.bic

    def rss_reduction(self, ref: "Score") -> float:
        return 1.0 - self.rss / ref.rss if ref.rss > 0 else 0.0


def held_out_score(fit: FitResult, obs: Observer, seg: Segments, sigma: torch.Tensor) -> Score:
    with torch.no_grad():
        pred = predict(fit.model.sim, fit.params, seg)
        e = robust(obs.error(pred[:, 1:], seg.meas[:, 1:]) / sigma)
    rss = float((e**2).sum())
    n = e.numel()
    n_eff = seg.count * e.shape[-1]
    k = len(fit.model.free)
    bic = n_eff * math.log(max(rss, 1e-300) / n) + k * math.log(n_eff)
    return Score(fit.model.name, fit.model.effects, k, rss, n, n_eff, bic)


def _noise(shape, phi: float, gen: torch.Generator) -> torch.Tensor:
    """Unit-variance noise of ``shape`` (S, T, c): white, or AR(1) with lag-1 correlation φ along T (filtered
    logs; fit.noise_model), stationary from the first sample."""
    e = torch.randn(shape, generator=gen, dtype=DTYPE)
    if phi <= 0 or len(shape) < 3:
        return e
    out = [e[:, 0]]
    c = math.sqrt(1 - phi * phi)
    for t in range(1, shape[1]):
        out.append(phi * out[-1] + c * e[:, t])
    return torch.stack(out, 1)


def _perturb(obs: Observer, states: torch.Tensor, noise: dict[str, float], gen: torch.Generator,
             phi: dict[str, float] | None = None) -> torch.Tensor:
    """Add measurement noise of the estimated level (and lag-1 correlation) to simulator states (S, T, X)."""
    phi = phi or {}
    out = states.clone()
    if not obs.rigid:
        for i, g in enumerate(obs.group_of_channel()):
            out[..., i] += noise[g] * _noise(states.shape[:-1] + (1,), phi.get(g, 0.0), gen)[..., 0]
        return out
    for idx, g in ((obs.i_pos, "position"), (obs.i_vel, "velocity"), (obs.i_om, "angular velocity")):
        out[..., idx] += noise[g] * _noise(states.shape[:-1] + (3,), phi.get(g, 0.0), gen)
    d = noise["attitude"] * _noise(states.shape[:-1] + (3,), phi.get("attitude", 0.0), gen)
    if obs.quat:
        q = states[..., obs.i_att]
        dq = torch.cat([torch.ones_like(d[..., :1]), 0.5 * d], -1)
        w1, x1, y1, z1 = q.unbind(-1)
        w2, x2, y2, z2 = dq.unbind(-1)
        qn = torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                          w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)
        out[..., obs.i_att] = qn / qn.norm(dim=-1, keepdim=True)
    else:
        out[..., obs.i_att] += d
    return out


def noise_floor(fit: FitResult, obs: Observer, seg: Segments, sigma: torch.Tensor, noise: dict[str, float],
                seed: int, replicas: int = BOOTSTRAP_REPLICAS, phi: dict[str, float] | None = None) -> float:
    """Held-out RSS expected from measurement noise alone if ``fit`` were the true model (bootstrap mean)."""
    gen = torch.Generator().manual_seed(int(seed))
    sim = fit.model.sim
    vals = []
    with torch.no_grad():
        clean = predict(sim, fit.params, seg)  # (S, H+1, X)
        for _ in range(replicas):
            noisy = _perturb(obs, clean, noise, gen, phi)
            fake = seg.with_states(consistent_start(sim, noisy[:, 0]), noisy)
            pred = predict(sim, fit.params, fake)
            e = robust(obs.error(pred[:, 1:], noisy[:, 1:]) / sigma)
            vals.append(float((e**2).sum()))
    return float(np.mean(vals))


def beats(a: Score, ref: Score) -> bool:
    return a.delta_bic(ref) >= DELTA_BIC_MIN and a.rss_reduction(ref) >= MIN_RSS_REDUCTION


@dataclass
class Decision:
    cause: str  # effect name, "a+b", "none" or "unexplained"
    selected: Score  # the model whose parameters and errors are reported as "extended"
    best_candidate: Score | None
    reason: str


def decide(base: Score, singles: list[Score], pairs: list[Score]) -> Decision:
    """Apply the decision rule of the module docstring (scores must carry ρ for base and candidates)."""
    ranked = sorted(singles + pairs, key=lambda s: s.bic)
    # the best single effect *that beats the base*: a one-parameter effect can have the lowest BIC yet miss the 5 %
    # RSS margin while another single beats the base by both
    winners = [s for s in singles if beats(s, base)]
    best_single = min(winners, key=lambda s: s.bic) if winners else None
    chosen = None
    if best_single is not None:
        chosen = best_single
        better_pairs = [p for p in pairs if best_single.name in p.name.split("+") and beats(p, best_single)]
        better_pairs += [p for p in pairs if p not in better_pairs and beats(p, best_single)]
        if better_pairs:
            chosen = min(better_pairs, key=lambda s: s.bic)
    best_any = ranked[0] if ranked else None
    if chosen is None:
        # a pair can beat the base even when no single does (two effects needed together)
        pair_wins = [p for p in pairs if beats(p, base)]
        if pair_wins:
            chosen = min(pair_wins, key=lambda s: s.bic)
    if chosen is None:
        if base.rho <= RHO_MAX:
            return Decision("none", base, best_any,
                            f"no candidate beats the base model (ΔBIC ≥ {DELTA_BIC_MIN:g} and ≥ {MIN_RSS_REDUCTION:.0%} "
                            f"lower held-out RSS) and the base residual is at the noise floor (ρ = {base.rho:.2f} ≤ {RHO_MAX})")
        return Decision("unexplained", base, best_any,
                        f"the base residual is {base.rho:.2f}× the noise floor (> {RHO_MAX}) and no candidate reduces it "
                        f"significantly")
    if chosen.rho > RHO_MAX:
        return Decision("unexplained", chosen, chosen,
                        f"{chosen.name} improves on the base (ΔBIC = {chosen.delta_bic(base):.1f}, held-out RSS −"
                        f"{chosen.rss_reduction(base):.0%}) but leaves {chosen.rho:.2f}× the noise floor (> {RHO_MAX}): "
                        f"a significant residual remains that no candidate accounts for")
    return Decision(chosen.name, chosen, chosen,
                    f"{chosen.name} beats the base model (ΔBIC = {chosen.delta_bic(base):.1f}, held-out RSS −"
                    f"{chosen.rss_reduction(base):.0%}) and leaves the residual at the noise floor (ρ = {chosen.rho:.2f})")


def check_dependence(decision: Decision, dependence) -> Decision:
    """A named cause (or ``none``) whose held-out residual still depends on a regressor becomes
    ``unexplained`` with the regressor in the reason (risp_tasks.diagnose.dependence)."""
    sig = [d for d in dependence if d.significant]
    if not sig:
        return decision
    d = sig[0]
    if decision.cause == "unexplained":  # already no name: say what the residual still depends on
        return Decision("unexplained", decision.selected, decision.best_candidate,
                        f"{decision.reason}; the held-out residual of {decision.selected.name} still depends on "
                        f"{d.regressor} (channel {d.channel}: p = {d.p_value:.1e}, η² = {d.eta2:.2f})")
    what = f"{decision.cause} lowers the residual" if decision.cause != "none" else "the base model reaches the noise floor"
    return Decision("unexplained", decision.selected, decision.best_candidate,
                    f"{what} ({decision.reason}), but its held-out residual still depends on {d.regressor} "
                    f"(channel {d.channel}: p = {d.p_value:.1e}, η² = {d.eta2:.2f}): not a confident name")


#: A fitted value within this fraction of the limits' span of a limit is reported as at its bound.
AT_BOUND = 0.01


def bound_flag(model, name: str, value: float) -> dict:
    """{"at_bound": "lower"/"upper"} when a fitted parameter sits at (within 1 % of) a limit of its search
    interval (the plausible range widened by its width; docs/diagnose.md §2), else {}."""
    i = model.free.index(name)
    lo, hi = float(model.lower[i]), float(model.upper[i])
    span = hi - lo if math.isfinite(hi - lo) else abs(value) + 1.0
    if math.isfinite(lo) and value - lo <= AT_BOUND * span:
        return {"at_bound": "lower", "limit": lo}
    if math.isfinite(hi) and hi - value <= AT_BOUND * span:
        return {"at_bound": "upper", "limit": hi}
    return {}


def estimate_note(decision: Decision, estimated_by: dict | None, noise_info: dict) -> Decision:
    """An ``unexplained`` verdict on a trajectory that ``risp-task estimate`` read from a video (the sidecar's
    ``estimated_by``) names the estimates' own error as a possible reason.  A network's reading of an unseen look
    errs by a bias that drifts slowly with the motion (lag-1 correlation near 1), not by the white noise the
    noise floor assumes, so a residual above that floor may be the reading's error rather than missing physics
    (docs/tasks.md §Video → diagnosis).  Other verdicts are returned unchanged."""
    if decision.cause != "unexplained" or not estimated_by:
        return decision
    model = estimated_by.get("model") if isinstance(estimated_by, dict) else None
    model = model.get("path") if isinstance(model, dict) else model  # {path, sha256} as estimate writes it, or a path
    phi = {g: v for g, v in (noise_info.get("lag1_correlation_estimate") or {}).items() if v > 0}
    errors = ("whose errors are correlated in time (lag-1 correlation of the smoothing residuals: "
              + ", ".join(f"{g} {v:.2f}" for g, v in phi.items()) + "), not the white noise the floor assumes"
              if phi else "whose errors in an unseen look are a bias that drifts with the motion, which the white-noise "
                          "floor does not model")
    return Decision("unexplained", decision.selected, decision.best_candidate,
                    f"{decision.reason}; the data are a network's estimates from a video (risp-task estimate"
                    f"{', model ' + str(model) if isinstance(model, str) and model else ''}), {errors}: the residual "
                    f"may be the estimate noise rather than missing physics")


def estimate_force_note(decision: Decision, estimated_by: dict | None, values: dict, mass: float | None,
                        gravity: float = GRAVITY) -> Decision:
    """A ``wind`` named on a network's estimates from a video says which attitude bias would fit the same.

    Through the known thrust T ≈ m g, an attitude reading tilted by β predicts a horizontal acceleration g tan β,
    i.e. the force m g tan β; a bias that is constant in this look (the network's error in an unseen look is
    such a bias) is therefore one parameter with a constant force, and the fit cannot tell them apart.  The note
    gives the tilt β = atan(|F_h| / (m g)) that the fitted horizontal force F_h = (f_x, f_y) equals, so the verdict
    can be held against the constant part of the network's thrust-axis error in that look (its yaw error and the
    part that varies through the flight do not act like a force; docs/tasks.md §Video → diagnosis).  Other
    verdicts, data without the ``estimated_by`` provenance, or an unknown mass leave the decision unchanged."""
    if not estimated_by or "wind" not in decision.selected.effects or not mass or mass <= 0:
        return decision
    f_h = math.hypot(float(values.get("wind.fx", 0.0)), float(values.get("wind.fy", 0.0)))
    tilt = math.degrees(math.atan2(f_h, mass * gravity))
    return Decision(decision.cause, decision.selected, decision.best_candidate,
                    f"{decision.reason}; the data are a network's estimates from a video, where a constant bias of the "
                    f"estimated attitude fits the same as a constant force: this force's horizontal part ({f_h:.2f} N "
                    f"on {mass:.3g} kg) equals a tilt of {tilt:.1f}°, so it is wind only if the network's reading of "
                    f"the thrust axis in this look is biased by well less than that")


def runner_up_note(decision: Decision, scores: list[Score]) -> tuple[Decision, dict | None]:
    """A named cause whose nearest rival (a model that does not contain it) is within ΔBIC < DELTA_BIC_MIN
    keeps its name — it is still the best — but the reason says the data hardly separate the two."""
    if decision.cause in ("none", "unexplained"):
        return decision, None
    named = set(decision.selected.effects)
    rivals = [sc for sc in scores if sc.effects and not named & set(sc.effects)]
    if not rivals:
        return decision, None
    rival = min(rivals, key=lambda sc: sc.bic)
    gap = rival.bic - decision.selected.bic
    info = {"model": rival.name, "delta_bic_to_selected": gap}
    if gap >= DELTA_BIC_MIN:
        return decision, info
    return Decision(decision.cause, decision.selected, decision.best_candidate,
                    f"{decision.reason}; runner-up {rival.name} is only ΔBIC = {gap:.1f} behind (< {DELTA_BIC_MIN:g}): "
                    f"these data hardly separate the two"), info
