"""Fitting simulator parameters to measured trajectories by multiple shooting (docs/diagnose.md §Fit).

A trajectory is cut into short segments of H samples.  Each segment starts from the *measured* state and is
integrated by the simulator (k sub-steps per sample); the residual is the normalised prediction error at the
H following samples,

    e[s, h, c] = (obs(Φ_θ^{h·k}(x̃_s))_c − obs(x̃_{s+h})_c) / σ_c ,     h = 1 … H,

with σ_c the measurement-noise level of channel c (estimated from the data, :func:`estimate_noise`).
Short segments keep the problem well conditioned (no chaotic divergence of long rollouts, no contact
timing mismatch accumulating).  θ is found by Levenberg–Marquardt on ½‖e‖²; the Jacobian ∂e/∂θ is exact,
by forward-mode automatic differentiation through the simulator (one tangent per free parameter).
A cluster-robust (sandwich) covariance gives the parameter uncertainty (:func:`parameter_std`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.autograd.forward_ad as fwAD

from risp_data.errors import RispError

from ..measured import Trajectory, quat_mul, sampling_step
from .adapter import Observer, consistent_start, sim_actions, sim_states

DTYPE = torch.float64

#: c = ROBUST_SCALE × (a segment's expected χ²): segments beyond ~c count logarithmically.
ROBUST_SCALE = 10.0

#: Samples of command history used to initialise latent effect states (motor thrusts) at a segment start.
WARMUP_SAMPLES = 30

#: Lower limits on the estimated noise level per channel group (SI units): data that is exactly
#: noise-free (or quantised) must not get infinite weight.
NOISE_FLOOR = {"position": 1e-5, "attitude": 1e-5, "velocity": 1e-4, "angular velocity": 1e-4,
               "coordinate": 1e-6, "rate": 1e-5}


@dataclass(frozen=True)
class FitConfig:
    horizon: int = 10  # H: samples per multiple-shooting segment
    stride: int | None = None  # samples between segment starts (default H: non-overlapping)
    max_segments: int = 600  # cap on segments used (seeded random subset beyond it)
    max_iters: int = 25  # Levenberg–Marquardt iterations
    tol: float = 1e-4  # stop when the relative decrease of ‖e‖² falls below this


@dataclass
class Segments:
    """Multiple-shooting segments cut from measured trajectories (all float64 tensors)."""

    s0: torch.Tensor  # (S, X) measured simulator state at the segment start
    actions: torch.Tensor | None  # (S, H·k, A) zero-order hold of the measured command
    meas: torch.Tensor  # (S, H+1, X) measured states at the samples of the segment (row 0 = s0)
    traj_index: np.ndarray  # (S,) index of the source trajectory
    start: np.ndarray  # (S,) sample index of the segment start
    horizon: int
    k: int  # simulator sub-steps per sample
    sample_dt: float
    past_actions: torch.Tensor | None = None  # (S, W·k, A) commands of the W samples before the start

    def with_states(self, s0: torch.Tensor, meas: torch.Tensor) -> "Segments":
        return dataclasses.replace(self, s0=s0, meas=meas)

    @property
    def count(self) -> int:
        return int(self.s0.shape[0])


#: a segment is simulated at a fixed step: one whose samples stray from the fixed-rate grid by more than this fraction
#: of a step (a dropped sample: a whole step) is not used (docs/diagnose.md §3)
STEP_TOLERANCE = 0.5


def even_starts(t: np.ndarray, horizon: int, chunk: int = 65536) -> np.ndarray:
    """(N,) bool: whether samples i … i + ``horizon`` lie on the fixed-rate grid from sample i, each within
    STEP_TOLERANCE·Δ of t[i] + h·Δ (Δ: measured.sampling_step).  A dropped sample shifts all later ones by Δ and
    fails; timestamps rounded to the clock's tick (steps of 2 and 3 ms at 400 Hz) do not accumulate and pass."""
    t = np.asarray(t, np.float64)
    n, out = len(t), np.zeros(len(t), bool)
    if n <= horizon:
        return out
    step = sampling_step(t)
    drift = t - t[0] - step * np.arange(n)  # the time's departure from the fixed-rate grid
    windows = np.lib.stride_tricks.sliding_window_view(drift, horizon + 1)  # (n − horizon, horizon + 1), a view
    for a in range(0, len(windows), chunk):  # chunks: a long log's windows would take gigabytes at once
        w = windows[a:a + chunk]
        out[a:a + len(w)] = np.abs(w - w[:, :1]).max(1) <= STEP_TOLERANCE * step
    return out


def longest_even(trajs: list[Trajectory], up_to: int) -> int:
    """The largest h ≤ ``up_to`` for which some trajectory has a window of h even steps (:func:`even_starts`; 0 if
    none): the rollout error's horizon is cut to it rather than failing after every fit."""
    lo, hi = 0, up_to
    while lo < hi:  # an even window of h steps holds one of h − 1: bisect
        mid = (lo + hi + 1) // 2
        if any(even_starts(tr.t, mid).any() for tr in trajs):
            lo = mid
        else:
            hi = mid - 1
    return lo


def make_segments(sim, trajs: list[Trajectory], horizon: int, k: int, stride: int | None = None,
                  max_segments: int | None = None, rng: np.random.Generator | None = None,
                  params: torch.Tensor | None = None) -> Segments:
    """Cut every trajectory into segments of ``horizon`` samples starting every ``stride`` samples; a segment
    that crosses a dropped sample or an uneven step (:func:`even_starts`) is left out, as the model steps at one rate.

    ``params`` (P,): the model's parameters, used to convert measured thrusts to commands.

    When the simulator's library has effects with latent states (quadrotor motor_lag: rotor thrusts that
    are not measured), segments start only after the first WARMUP_SAMPLES samples of each trajectory, for
    every model of that simulator alike: the latent state at the start of a recording is unknown (on
    independent data the rotors' initial thrust was off by 3 N), and the warm-up filter needs real history.
    """
    stride = stride or horizon
    latent = any(e.state_names for e in sim.spec.available_effects.values())
    # choose the segments first (index pairs only), then build just those: a 200 MB log has ~10⁵ segments
    # and materialising all of them before subsampling took gigabytes
    pairs, any_start = [], False
    for j, tr in enumerate(trajs):
        has_actions = sim.action_dim > 0
        first = WARMUP_SAMPLES if latent and has_actions and tr.n - WARMUP_SAMPLES > 2 * horizon else 0
        starts = range(first, tr.n - horizon, stride)
        even = even_starts(tr.t, horizon)
        pairs += [(j, i) for i in starts if even[i]]
        any_start = any_start or len(starts) > 0
    if not pairs:
        if any_start:  # there were starts, and none was even
            raise RispError(f"no segment of {horizon + 1} evenly spaced samples: every one crosses a dropped sample or "
                            f"strays more than {STEP_TOLERANCE:.0%} of a step from the fixed-rate grid (the simulator "
                            f"steps at a fixed rate); resample the data to a fixed rate or use a smaller --horizon")
        longest = max(trajs, key=lambda tr: tr.n)
        raise RispError(f"no trajectory is longer than the segment horizon ({horizon} samples): the longest, "
                        f"{longest.name}, has {longest.n}; use a smaller --horizon")
    idx = np.arange(len(pairs))
    if max_segments is not None and len(idx) > max_segments:
        if rng is None:
            raise ValueError("a generator is needed to subsample segments")
        idx = np.sort(rng.choice(len(idx), size=max_segments, replace=False))
    chosen = [pairs[i] for i in idx]
    s0, acts, past, meas = [], [], [], []
    for j in sorted({j for j, _ in chosen}):
        tr = trajs[j]
        a = sim_actions(sim, tr, params)
        x = sim_states(sim, tr, a)
        if a is not None:
            a_pad = np.concatenate([np.repeat(a[:1], WARMUP_SAMPLES, 0), a], 0)
        for _, i in (p for p in chosen if p[0] == j):
            s0.append(x[i])
            meas.append(x[i : i + horizon + 1])
            if a is not None:
                acts.append(np.repeat(a[i : i + horizon], k, axis=0))
                past.append(np.repeat(a_pad[i : i + WARMUP_SAMPLES], k, axis=0))
    t = lambda arr: torch.as_tensor(np.stack(arr), dtype=DTYPE)  # noqa: E731
    return Segments(
        s0=consistent_start(sim, t(s0)),
        actions=t(acts) if acts else None,
        past_actions=t(past) if past else None,
        meas=t(meas),
        traj_index=np.asarray([j for j, _ in chosen]),
        start=np.asarray([i for _, i in chosen]),
        horizon=horizon,
        k=k,
        sample_dt=float(np.median([tr.dt for tr in trajs])),
    )


# ------------------------------------------------------------------------------------------------
# measurement noise
# ------------------------------------------------------------------------------------------------
#: A lag-1 noise correlation φ below this is treated as white noise (φ = 0).
MIN_NOISE_CORRELATION = 0.2


def _sg_residuals(sim, trajs: list[Trajectory], window: int) -> dict[str, list[np.ndarray]]:
    """Centre residuals (n, c) of a local quadratic (Savitzky–Golay) fit, per channel group and trajectory."""
    from scipy.signal import savgol_coeffs

    obs = Observer(sim)
    coef = savgol_coeffs(window, 2)
    out: dict[str, list[np.ndarray]] = {g: [] for g in obs.groups}
    for tr in trajs:
        if tr.n < window + 2:
            continue
        if obs.rigid:
            series = {"position": tr.pos, "attitude": tr.quat, "velocity": tr.vel, "angular velocity": tr.omega}
        else:
            x = sim_states(sim, tr, sim_actions(sim, tr))
            series = {g: x[:, list(idx)] for g, idx in obs.groups.items()}
        for g, y in series.items():
            smooth = np.stack([np.convolve(y[:, c], coef[::-1], mode="valid") for c in range(y.shape[1])], 1)
            centre = y[window // 2 : len(y) - window // 2]
            if obs.rigid and g == "attitude":
                # rotation vector between the smoothed and the measured attitude, 2·Im(q_s* ⊗ q)
                smooth = smooth / np.linalg.norm(smooth, axis=1, keepdims=True)
                rel = quat_mul(smooth * np.array([1.0, -1.0, -1.0, -1.0]), centre)
                r = 2.0 * np.sign(rel[:, :1] + 1e-300) * rel[:, 1:]
            else:
                r = centre - smooth
            out[g].append(r)
    return out


def _sg_noise_factors(window: int, phi: float) -> tuple[float, float]:
    """For AR(1) noise of unit variance and lag-1 correlation φ: (variance of the SG centre residual,
    its lag-1 autocorrelation).  r_t = Σ_i d_i n_{t+i} with d = δ_centre − SG coefficients."""
    from scipy.signal import savgol_coeffs

    d = -savgol_coeffs(window, 2)
    d[window // 2] += 1.0
    i = np.arange(window)
    cov0 = float(d @ (phi ** np.abs(i[:, None] - i[None, :])) @ d)
    cov1 = float(d @ (phi ** np.abs(i[:, None] - i[None, :] - 1)) @ d)
    return cov0, cov1 / cov0


def noise_model(sim, trajs: list[Trajectory], window: int = 7, declared: dict | None = None,
                declared_phi: float = 0.0) -> tuple[dict, dict, dict]:
    """(σ per group, lag-1 correlation φ per group, description) of the measurement noise (docs §4).

    Declared (sidecar ``measurement_noise``: {group: σ}, optional ``measurement_noise_correlation``: φ): used
    as given for the groups it names; the noise-floor bootstrap then draws AR(1) noise with that φ.
    Estimated: the robust variance of the Savitzky–Golay centre residuals (white-noise formula).  Their lag-1
    autocorrelation is compared with white noise's: an AR(1) φ is fitted to it and reported
    (``lag1_correlation_estimate``, ``time_correlated``) but **not used** — on fast tumbling or contact-rich
    data the 7-sample quadratic leaves structured residuals that look like φ ≈ 1 (synthetic cube tosses with
    white noise gave φ̂ = 0.99 and a 12× too large σ when it was used).
    """
    res = _sg_residuals(sim, trajs, window)
    grid = np.linspace(0.0, 0.99, 100)
    table = [_sg_noise_factors(window, f)[1] for f in grid]
    var0 = _sg_noise_factors(window, 0.0)[0]  # = 1 − h
    sigma, phi_hat = {}, {}
    for g, rs in res.items():
        if not rs:
            raise RispError(f"trajectories are too short to estimate the measurement noise (need > {window + 2} samples)")
        r = np.concatenate(rs)
        mad = np.median(np.abs(r)) + 1e-300
        clipped = [np.clip(x, -5 * mad / 0.6745, 5 * mad / 0.6745) for x in rs]  # impacts must not set φ
        num = sum(float((x[1:] * x[:-1]).sum()) for x in clipped)
        den = sum(float((x * x).sum()) for x in clipped)
        ac = num / max(den, 1e-300)
        f = float(grid[int(np.argmin([abs(t - ac) for t in table]))])
        phi_hat[g] = f if f >= MIN_NOISE_CORRELATION else 0.0
        var = np.median(r**2) / 0.4549 / var0
        sigma[g] = float(max(np.sqrt(var), NOISE_FLOOR.get(g, 1e-8)))
    phi = {g: 0.0 for g in sigma}
    unknown = [g for g in (declared or {}) if g not in sigma]
    if unknown:  # a misspelt group ("positon") was silently estimated instead of taken as declared
        raise RispError(f"sidecar key 'measurement_noise' names {', '.join(map(repr, unknown))}, not a channel group of "
                        f"this model; its groups are: {', '.join(sigma)}")
    declared_groups = [g for g in (declared or {}) if g in sigma]
    for g in declared_groups:
        sigma[g] = float(declared[g])
        phi[g] = float(declared_phi)
    if not declared_groups:
        source = "estimated (Savitzky–Golay residuals, white noise)"
    elif len(declared_groups) < len(sigma):
        source = "declared in the sidecar (others estimated)"
    else:
        source = "declared in the sidecar"
    info = {"source": source, "declared_groups": declared_groups, "lag1_correlation": dict(phi),
            "lag1_correlation_estimate": phi_hat, "time_correlated": any(v > 0 for v in phi_hat.values())}
    return sigma, phi, info


def estimate_noise(sim, trajs: list[Trajectory], window: int = 7) -> dict[str, float]:
    """Measurement-noise standard deviation per channel group (:func:`noise_model`, estimated)."""
    return noise_model(sim, trajs, window)[0]


def channel_sigma(obs: Observer, noise: dict[str, float]) -> torch.Tensor:
    return torch.tensor([noise[g] for g in obs.group_of_channel()], dtype=DTYPE)


# ------------------------------------------------------------------------------------------------
# the model: which parameters are free, how they are scaled
# ------------------------------------------------------------------------------------------------
@dataclass
class Model:
    """A simulator with some effects switched on, its fixed parameter values and its free parameters.

    Free parameters are optimised in a scaled space θ = θ₀ + scale ⊙ z (z ≈ O(1)) and kept inside
    their plausible ranges by projection.
    """

    sim: object
    base: torch.Tensor  # (P,) all parameter values (fixed ones from the sidecar / defaults)
    free: tuple[str, ...]
    scale: torch.Tensor  # (F,)
    lower: torch.Tensor  # (F,)
    upper: torch.Tensor  # (F,)
    effects: tuple[str, ...] = ()
    #: per free parameter, the plausible range (lo, hi) of an effect's parameter, None for a base parameter:
    #: the start search (:func:`grid_start`) scans these
    plausible: tuple = ()
    free_index: list[int] = field(default_factory=list)

    def __post_init__(self):
        self.free_index = [self.sim.param_index(n) for n in self.free]
        # keep a hair inside the limits: θ = θ₀ + scale·z is recomputed from z and may round outward
        pad = 1e-9 * (1.0 + torch.abs(self.lower))
        self.lower = torch.where(torch.isfinite(self.lower), self.lower + pad, self.lower)
        pad = 1e-9 * (1.0 + torch.abs(self.upper))
        self.upper = torch.where(torch.isfinite(self.upper), self.upper - pad, self.upper)

    @property
    def name(self) -> str:
        return "+".join(self.effects) if self.effects else "base"

    def params(self, z: torch.Tensor) -> torch.Tensor:
        """z (F,) -> full parameter vector (P,), differentiable in z."""
        if not self.free:
            return self.base
        theta = self.base[self.free_index] + self.scale * z
        p = self.base.clone()
        return p.index_put((torch.tensor(self.free_index),), theta)

    def clamp(self, z: torch.Tensor) -> torch.Tensor:
        theta = self.base[self.free_index] + self.scale * z
        theta = torch.maximum(torch.minimum(theta, self.upper), self.lower)
        return (theta - self.base[self.free_index]) / self.scale


# ------------------------------------------------------------------------------------------------
# residuals and Levenberg–Marquardt
# ------------------------------------------------------------------------------------------------
def latent_start(sim, params: torch.Tensor, seg: Segments) -> torch.Tensor:
    """Start states with the unmeasured (latent) entries of enabled effects filled in from the past.

    quadrotor ``motor_lag``: the rotor thrusts f are not measured (the f columns are the commands);
    they are the effect's own first-order filter f ← f + (1 − e^(−h/τ))·(k_f·u − f) run over the
    commands of the WARMUP_SAMPLES samples before the segment, from steady state — differentiable in τ.
    """
    if "motor_lag" not in getattr(sim, "effects", ()) or seg.past_actions is None:
        return seg.s0
    names = list(sim.state_names)
    idx = [names.index(n) for n in sim.spec.available_effects["motor_lag"].state_names]
    tau = params[sim.param_index("motor_lag.tau")]
    k_f = params[sim.param_index("k_f")]
    alpha = -torch.expm1(-sim.dt / tau)
    u = seg.past_actions[..., : len(idx)]  # (S, W·k, 4) rotor commands, or (S, W·k, 1) collective
    target = k_f * u
    if "k_f2" in sim.param_names:  # quadratic thrust map
        target = target + params[sim.param_index("k_f2")] * u * u
    f = target[:, 0]
    for j in range(1, target.shape[1]):
        f = f + alpha * (target[:, j - 1] - f)
    f = f + alpha * (target[:, -1] - f)
    s0 = seg.s0.clone()
    s0[:, idx] = f
    return s0


def predict(sim, params: torch.Tensor, seg: Segments, horizon: int | None = None) -> torch.Tensor:
    """Simulated states at the segment's samples, (S, H+1, X), from the measured start states."""
    H = seg.horizon if horizon is None else horizon
    S = seg.count
    p = params.unsqueeze(0).expand(S, -1)
    acts = None if seg.actions is None else seg.actions[:, : H * seg.k]
    states = sim.rollout(p, latent_start(sim, params, seg), acts, H * seg.k)
    return states[:, :: seg.k]


def robust(e: torch.Tensor) -> torch.Tensor:
    """Segment-level robust residuals ẽ with ‖ẽ_s‖² = ρ(r_s), r_s = ‖e_s‖² (docs/diagnose.md §3).

    ρ(r) = c·ln(1 + r/c), c = ROBUST_SCALE·H·C (H·C: a segment's expected χ² under pure noise): ≈ r for
    ordinary segments, logarithmic for the few whose outcome is chaotic in the noise (a tumbling cube's
    impact decided by which corner lands first), so that those neither dominate the fit nor the score.
    """
    r = (e**2).sum(dim=(1, 2), keepdim=True)  # (S, 1, 1)
    c = ROBUST_SCALE * e.shape[1] * e.shape[2]
    x = r / c
    # ρ(r)/r = ln(1 + x)/x, → 1 as x → 0
    factor = torch.where(x > 1e-8, torch.log1p(x) / torch.clamp(x, min=1e-8), 1.0 - 0.5 * x)
    return e * torch.sqrt(factor)


def residuals(sim, obs: Observer, params: torch.Tensor, seg: Segments, sigma: torch.Tensor) -> torch.Tensor:
    """Robust normalised multiple-shooting residuals ẽ (S, H, C)."""
    pred = predict(sim, params, seg)
    return robust(obs.error(pred[:, 1:], seg.meas[:, 1:]) / sigma)


@dataclass
class FitResult:
    model: Model
    z: torch.Tensor
    params: torch.Tensor  # (P,) fitted full parameter vector
    values: dict[str, float]  # free parameter -> fitted value
    stds: dict[str, float]  # free parameter -> 1-σ uncertainty (cluster-robust sandwich)
    rss: float  # fitting-data ‖e‖²
    n: int
    iterations: int
    history: list[float]


def _jacobian(fn, z: torch.Tensor) -> torch.Tensor:
    """J (n, F) of fn: R^F -> R^n by forward mode, one tangent per column."""
    cols = []
    with fwAD.dual_level():
        for j in range(z.numel()):
            tangent = torch.zeros_like(z)
            tangent[j] = 1.0
            out = fn(fwAD.make_dual(z, tangent))
            cols.append(fwAD.unpack_dual(out).tangent.reshape(-1))
    return torch.stack(cols, 1)


def fit_model(model: Model, obs: Observer, seg: Segments, sigma: torch.Tensor, cfg: FitConfig,
              progress=None) -> FitResult:
    """Levenberg–Marquardt on ½‖e(z)‖² with the exact forward-mode Jacobian, from two starts: the library
    defaults and the best point of a scan of the effect parameters (:func:`grid_start`); the lower ‖ẽ‖² wins."""
    sim = model.sim
    fn = lambda z: residuals(sim, obs, model.params(z), seg, sigma).reshape(-1)  # noqa: E731
    F = len(model.free)
    z = torch.zeros(F, dtype=DTYPE)
    with torch.no_grad():
        r = fn(z)
    rss = float((r**2).sum())
    if not F:
        return _result(model, fn, seg, z, r, rss, 0, [rss])
    try:
        J0 = _jacobian(fn, z)
    except (RuntimeError, NotImplementedError):
        # the simulator has no forward-mode derivative (e.g. an adjoint custom autograd Function)
        return _fit_lbfgs(model, fn, seg, cfg, z, rss)
    best = _levenberg_marquardt(model, fn, z, r, rss, cfg, progress, J0=J0)
    zg, rg, rssg = grid_start(model, fn, z, r, rss)
    if not torch.equal(zg, z):
        other = _levenberg_marquardt(model, fn, zg, rg, rssg, cfg, progress, history=[rss, rssg])
        if other[2] < best[2]:
            best = other
    return _result(model, fn, seg, *best)


def _levenberg_marquardt(model: Model, fn, z: torch.Tensor, r: torch.Tensor, rss: float, cfg: FitConfig,
                         progress=None, history: list[float] | None = None, J0: torch.Tensor | None = None):
    """LM iterations from z (J0: the Jacobian there, if known; docs/diagnose.md §3); returns
    (z, r, ‖ẽ‖², iterations, history)."""
    history = [rss] if history is None else list(history)
    it = 0
    lam = 1e-3
    for it in range(1, cfg.max_iters + 1):
        J = J0 if it == 1 and J0 is not None else _jacobian(fn, z)
        if not bool(torch.isfinite(J).all()):
            break  # the simulator is unstable around z: keep the last good point
        A = J.T @ J
        g = J.T @ r
        improved = False
        rel = 0.0
        for _ in range(8):  # λ from its current value up to ×4⁷
            D = torch.diag(torch.clamp(torch.diagonal(A), min=1e-12))
            try:
                step = torch.linalg.solve(A + lam * D, -g)
            except RuntimeError:
                lam *= 10
                continue
            if not bool(torch.isfinite(step).all()):
                lam *= 10
                continue
            z_new = model.clamp(z + step)
            with torch.no_grad():
                r_new = fn(z_new)
            rss_new = float((r_new**2).sum())
            if np.isfinite(rss_new) and rss_new < rss:
                improved = True
                rel = (rss - rss_new) / max(rss, 1e-300)
                z, r, rss = z_new, r_new, rss_new
                lam = max(lam / 3, 1e-9)
                break
            lam *= 4
        # a change below 0.1 in the normalised RSS (a χ² value) is statistically irrelevant
        if not improved or rel < cfg.tol or rel * rss < 0.1:
            # Gauss–Newton's curvature JᵀJ can exceed the loss's real curvature by orders of magnitude
            # where the rollout is chaotic (contact): its steps then stall although the gradient points
            # the right way.  A backtracking line search along the Jacobi-scaled gradient takes over.
            ls = _line_search(fn, model, z, rss, g, torch.diagonal(A))
            if ls is not None:
                z, r, rss_new = ls
                rel = (rss - rss_new) / max(rss, 1e-300)
                rss = rss_new
                improved = True
        history.append(rss)
        if progress is not None:
            progress(model.name, it, rss)
        if not improved or rel < cfg.tol or rel * rss < 0.1:
            break
    return z, r, rss, it, history


def _result(model: Model, fn, seg: Segments, z: torch.Tensor, r: torch.Tensor, rss: float, it: int,
            history: list[float]) -> FitResult:
    """The FitResult at z, with the parameters' uncertainties from the Jacobian there."""
    F = len(model.free)
    n = r.numel()
    params = model.params(z).detach()
    values = {name: float(params[i]) for name, i in zip(model.free, model.free_index)}
    stds = {}
    if F:
        J = _jacobian(fn, z)  # at the optimum: the sandwich needs J and r at the same point
        stds = parameter_std(model, J, r, seg) if bool(torch.isfinite(J).all()) else \
            {name: float("nan") for name in model.free}
    return FitResult(model, z.detach(), params, values, stds, rss, n, it, history)


#: Points per effect parameter of the start search: the midpoints of this many equal bins of its plausible range.
GRID_POINTS = 8


def grid_start(model: Model, fn, z: torch.Tensor, r: torch.Tensor, rss: float):
    """LM's second start: each effect parameter in turn set to the best of GRID_POINTS points of its
    plausible range (the midpoints of equal bins) or left at its current value (docs/diagnose.md §3).

    Where contact makes the loss rough, LM from the library default can stall far from the minimum: on a
    synthetic friction case (true μ = 0.41) it crawled from the default 0.3 for 8 iterations and stopped at
    a worse point with d_n at a third of its value; from the scan's best it reached the truth's RSS. The
    scan alone is no better start everywhere (a rough rolling-friction case ended higher from it), hence two.
    Costs GRID_POINTS evaluations of ‖ẽ‖² per effect parameter (no Jacobians). Returns (z, r, ‖ẽ‖²).
    """
    for j, rng in enumerate(model.plausible):
        if rng is None:
            continue
        lo, hi = rng
        for i in range(GRID_POINTS):
            theta = lo + (i + 0.5) * (hi - lo) / GRID_POINTS
            z_new = z.clone()
            z_new[j] = (theta - model.base[model.free_index[j]]) / model.scale[j]
            z_new = model.clamp(z_new)
            with torch.no_grad():
                r_new = fn(z_new)
            rss_new = float((r_new**2).sum())
            if np.isfinite(rss_new) and rss_new < rss:
                z, r, rss = z_new, r_new, rss_new
    return z, r, rss


def _line_search(fn, model: Model, z: torch.Tensor, rss: float, g: torch.Tensor, diag: torch.Tensor):
    """Backtracking along d = −g/√diag(JᵀJ), normalised to a largest entry of 1 (z units ≈ a quarter of
    the plausible range), then along each parameter's own axis (sign of d_j): steps 1, ½, … 1/32, the first
    that lowers ‖ẽ‖² is taken in each direction in turn.  None when no direction improves."""
    d = -g / torch.sqrt(torch.clamp(diag, min=1e-300))
    if not bool(torch.isfinite(d).all()) or float(d.abs().max()) == 0.0:
        return None
    # the joint direction first, then each parameter alone (the scaled gradient is often dominated by
    # one stiff parameter, e.g. the contact stiffness, while another, e.g. μ, is far from its optimum)
    directions = [d / d.abs().max()]
    for j in range(d.numel()):
        if float(d[j]) != 0.0:
            e = torch.zeros_like(d)
            e[j] = torch.sign(d[j])
            directions.append(e)
    best = None
    for direction in directions:
        for t in (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125):
            z_new = model.clamp(z + t * direction)
            with torch.no_grad():
                r_new = fn(z_new)
            rss_new = float((r_new**2).sum())
            if np.isfinite(rss_new) and rss_new < rss:
                z, rss, best = z_new, rss_new, (z_new, r_new, rss_new)
                break
    return best


#: Consecutive segments of one trajectory that form one cluster of the robust covariance.
CLUSTER_SEGMENTS = 2


def clusters(seg: Segments) -> np.ndarray:
    """(S,) cluster id of every segment: CLUSTER_SEGMENTS consecutive segments of one trajectory."""
    block = seg.start // (CLUSTER_SEGMENTS * seg.horizon)
    keys = seg.traj_index.astype(np.int64) * 1_000_000 + block
    return np.unique(keys, return_inverse=True)[1]


def parameter_std(model: Model, J: torch.Tensor, r: torch.Tensor, seg: Segments) -> dict[str, float]:
    """1-σ of the free parameters: cluster-robust (sandwich) covariance (docs/diagnose.md §6).

        Σ = (G/(G − F)) · A⁻¹ (Σ_g J_gᵀ r_g r_gᵀ J_g) A⁻¹,   A = JᵀJ,

    g over clusters of consecutive segments (residuals along a segment are correlated; model error makes
    them non-white), never below the plain Gauss–Newton s²·A⁻¹ with s² = RSS/(n − F).
    """
    F = J.shape[1]
    r = r.reshape(-1)
    n = r.numel()
    A_inv = torch.linalg.pinv(J.T @ J)
    cid = torch.as_tensor(np.repeat(clusters(seg), n // seg.count))
    G = int(cid.max()) + 1
    scores = torch.zeros(G, F, dtype=J.dtype).index_add_(0, cid, J * r[:, None])  # Σ_{i∈g} J_i r_i
    meat = scores.T @ scores * (G / max(G - F, 1))
    cov_sandwich = A_inv @ meat @ A_inv
    cov_gn = A_inv * float((r**2).sum()) / max(n - F, 1)
    var = torch.maximum(torch.diagonal(cov_sandwich), torch.diagonal(cov_gn))
    std = torch.sqrt(torch.clamp(var, min=0)) * model.scale
    return {name: float(v) for name, v in zip(model.free, std)}


def _fit_lbfgs(model: Model, fn, seg: Segments, cfg: FitConfig, z0: torch.Tensor, rss0: float) -> FitResult:
    """Fallback for simulators with reverse-mode derivatives only: L-BFGS-B on ½‖e‖² (exact gradient by
    backpropagation); the covariance uses L-BFGS's inverse-Hessian estimate in place of (JᵀJ)⁻¹."""
    from scipy.optimize import minimize

    history = [rss0]

    def f(zn):
        z = torch.tensor(zn, dtype=DTYPE, requires_grad=True)
        r = fn(z)
        loss = 0.5 * (r**2).sum()
        if not bool(torch.isfinite(loss)):
            return 1e300, np.zeros_like(zn)
        loss.backward()
        history.append(2 * float(loss.detach()))
        return float(loss.detach()), z.grad.numpy().copy()

    lo = ((model.lower - model.base[model.free_index]) / model.scale).numpy()
    hi = ((model.upper - model.base[model.free_index]) / model.scale).numpy()
    bounds = [(None if not np.isfinite(a) else float(a), None if not np.isfinite(b) else float(b)) for a, b in zip(lo, hi)]
    res = minimize(f, z0.numpy(), jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": 3 * cfg.max_iters})
    z = torch.tensor(res.x, dtype=DTYPE)
    with torch.no_grad():
        r = fn(z)
    rss = float((r**2).sum())
    n = r.numel()
    params = model.params(z).detach()
    values = {name: float(params[i]) for name, i in zip(model.free, model.free_index)}
    F = len(model.free)
    h_inv = torch.tensor(np.asarray(res.hess_inv.todense()), dtype=DTYPE)  # ≈ (JᵀJ)⁻¹ for ½‖e‖²
    cov_z = h_inv * rss / max(n - F, 1) * seg.horizon
    std = torch.sqrt(torch.clamp(torch.diagonal(cov_z), min=0)) * model.scale
    stds = {name: float(v) for name, v in zip(model.free, std)}
    return FitResult(model, z, params, values, stds, rss, n, int(res.nit), history)
