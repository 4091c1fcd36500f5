"""The diagnose pipeline: fit the base model, analyse residuals, try the candidate effects, name the cause.

``DiagnoseConfig`` (plain values) -> :func:`diagnose` -> report dict (and files under ``out``).
Method, statistics and thresholds: docs/diagnose.md.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass

from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from risp_data.errors import RispError

from ..measured import Trajectory, load_measured
from . import candidates as cands
from .adapter import Observer, calibrate_floor
from .fit import FitConfig, FitResult, channel_sigma, fit_model, longest_even, make_segments, noise_model
from .residuals import accel_rms, group_rms, one_step, rollout_error
from .dependence import residual_dependence
from .select import (RHO_MAX, Score, bound_flag, check_dependence, decide, estimate_force_note, estimate_note,
                     held_out_score, noise_floor, runner_up_note)


#: Held-out one-step residuals are scored on at most this many × --max-segments samples (a seeded subset).
ONE_STEP_PER_SEGMENT = 10


@dataclass(frozen=True)
class DiagnoseConfig:
    data: tuple[str, ...]
    env: str
    out: str | None
    seed: int
    held_out: float = 0.3  # fraction of trajectories (or of the time span of a single one) held out
    horizon: int = 10  # multiple-shooting segment length [samples]
    rollout_horizon: int | None = None  # open-loop horizon of the reported rollout error (default 3·horizon)
    max_segments: int = 600
    max_iters: int = 25
    pairs_top: int = 3  # pairs are formed among this many best single effects
    effects: tuple[str, ...] | None = None  # restrict the candidate library (None: all of the simulator's)
    limit: int | None = None  # use only the first N files
    floor_offset: float | str = "auto"  # cube: floor height in the data's frame [m], or "auto" (resting frames)
    side: float | None = None  # cube sidecar overrides [m]
    mass: float | None = None  # [kg]
    plots: bool = True
    progress: bool = True


# ------------------------------------------------------------------------------------------------
# split
# ------------------------------------------------------------------------------------------------
#: the fewest samples each part of a trajectory split by time may have
MIN_PART = 10


def split_trajectories(trajs: list[Trajectory], held_out: float, seed: int) -> tuple[list[Trajectory], list[Trajectory], dict]:
    """Whole trajectories (seeded permutation) when there are several, else the last part of the one."""
    if not 0.0 < held_out < 1.0:
        raise RispError(f"--held-out must lie in (0, 1), got {held_out}")
    if len(trajs) >= 2:
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1]))
        order = rng.permutation(len(trajs))
        n_held = min(max(1, int(round(held_out * len(trajs)))), len(trajs) - 1)
        held = sorted(order[:n_held].tolist())
        fit = sorted(order[n_held:].tolist())
        info = {"mode": "trajectories", "fit": [trajs[i].name for i in fit], "held_out": [trajs[i].name for i in held],
                "held_out_fraction": held_out, "seed": int(seed)}
        return [trajs[i] for i in fit], [trajs[i] for i in held], info
    tr = trajs[0]
    cut = int(round((1.0 - held_out) * tr.n))
    if cut < MIN_PART or tr.n - cut < MIN_PART:
        need = next(n for n in range(2 * MIN_PART, 10**9) if MIN_PART <= int(round((1.0 - held_out) * n)) <= n - MIN_PART)
        raise RispError(f"{tr.path}: too short ({tr.n} samples) to split by time into fitting and held-out parts of "
                        f"at least {MIN_PART} samples each at --held-out {held_out:g}: it needs {need} (or give several "
                        "trajectories, which are split whole)")
    info = {"mode": "time", "fit": [f"{tr.name}[0:{cut}]"], "held_out": [f"{tr.name}[{cut}:{tr.n}]"],
            "split_time_s": float(tr.t[cut]), "held_out_fraction": held_out, "seed": int(seed)}
    return [tr.slice(0, cut, "[fit]")], [tr.slice(cut, tr.n, "[held-out]")], info


# ------------------------------------------------------------------------------------------------
# one model: fit, score, noise floor, errors
# ------------------------------------------------------------------------------------------------
@dataclass
class Evaluated:
    fit: FitResult
    score: Score
    k: int
    obs: Observer
    seg_held: object = None
    sigma: torch.Tensor | None = None


def _segments(model, trajs, cfg: DiagnoseConfig, k: int, salt: int):
    rng = np.random.default_rng(np.random.SeedSequence([int(cfg.seed), 2, salt]))
    return make_segments(model.sim, trajs, cfg.horizon, k, max_segments=cfg.max_segments, rng=rng, params=model.base)


def evaluate_model(effects: tuple[str, ...], fit_trajs, held_trajs, cfg: DiagnoseConfig, noise, bar=None,
                   phi: dict | None = None) -> Evaluated:
    sidecar = fit_trajs[0].sidecar
    model, k = cands.build_model(cfg.env, effects, sidecar, fit_trajs[0].dt)
    obs = Observer(model.sim)
    sigma = channel_sigma(obs, noise)
    seg_fit = _segments(model, fit_trajs, cfg, k, salt=0)
    seg_held = _segments(model, held_trajs, cfg, k, salt=1)

    def progress(name, it, rss):
        if bar is not None:
            bar.set_postfix_str(f"{name} it {it} rss {rss:.4g}")

    fit = fit_model(model, obs, seg_fit, sigma, FitConfig(horizon=cfg.horizon, max_segments=cfg.max_segments,
                                                          max_iters=cfg.max_iters), progress)
    score = held_out_score(fit, obs, seg_held, sigma)
    score.noise_rss = noise_floor(fit, obs, seg_held, sigma, noise, seed=cfg.seed, phi=phi)
    score.rho = score.rss / max(score.noise_rss, 1e-300)
    return Evaluated(fit, score, k, obs, seg_held, sigma)


def errors(ev: Evaluated, held_trajs, cfg: DiagnoseConfig) -> dict:
    """Held-out one-step residuals and multi-step rollout error of a fitted model (SI units)."""
    sim, params = ev.fit.model.sim, ev.fit.params
    os_ = one_step(sim, ev.obs, params, held_trajs, ev.k, max_samples=ONE_STEP_PER_SEGMENT * cfg.max_segments,
                   seed=cfg.seed)
    H_r = cfg.rollout_horizon or 3 * cfg.horizon
    H_r = min(H_r, min(tr.n for tr in held_trajs) - 1)
    H_r = max(1, longest_even(held_trajs, H_r))  # dropped samples: the longest even stretch, not a failure
    sigma = ev.sigma.numpy() if ev.sigma is not None else 1.0
    roll = rollout_error(sim, ev.obs, params, held_trajs, ev.k, H_r, sigma=sigma, max_segments=cfg.max_segments,
                         seed=cfg.seed)
    return {
        "one_step": group_rms(ev.obs, os_.error),
        "one_step_acceleration": accel_rms(ev.obs, os_),
        "rollout": roll["groups"],
        "rollout_normalized": roll["normalized"],
        "rollout_horizon_samples": int(H_r),
        "rollout_horizon_s": float(H_r * held_trajs[0].dt),
        "normalized_rss": ev.score.rss,
        "noise_floor_ratio": ev.score.rho,
    }


def gain(base: dict, ext: dict) -> dict:
    """Relative reduction 1 − ext/base of every held-out error (positive = the extended model is better)."""
    out = {}
    for key in ("one_step", "one_step_acceleration", "rollout"):
        out[key] = {g: (1.0 - ext[key][g] / base[key][g]) if base[key][g] > 0 else 0.0 for g in base[key]}
    out["normalized_rss"] = 1.0 - ext["normalized_rss"] / base["normalized_rss"] if base["normalized_rss"] > 0 else 0.0
    out["rollout_normalized"] = 1.0 - ext["rollout_normalized"] / base["rollout_normalized"] \
        if base["rollout_normalized"] > 0 else 0.0
    return out


def _score_row(s: Score, base: Score) -> dict:
    return {"model": s.name, "effects": list(s.effects), "k": s.k, "held_out_rss": s.rss, "bic": s.bic,
            "delta_bic": s.delta_bic(base), "rss_reduction": s.rss_reduction(base), "noise_floor_ratio": s.rho}


# ------------------------------------------------------------------------------------------------
# the pipeline
# ------------------------------------------------------------------------------------------------
def diagnose(cfg: DiagnoseConfig) -> dict:
    """Run the whole diagnosis; writes report.md/report.json/plots under ``cfg.out`` when it is set.

    Runs single-threaded: the simulators' many tiny batched ops are 10–100× slower with intra-op
    threads on a loaded 2-core machine (thread hand-off dominates); the previous setting is restored.
    """
    if not 0 <= int(cfg.seed) < 2**63:  # torch.manual_seed takes a signed 64-bit integer
        raise RispError(f"--seed must be in [0, 2**63), got {cfg.seed}")
    if cfg.pairs_top < 0:
        raise RispError(f"--pairs-top must be >= 0 (0: no effect pairs), got {cfg.pairs_top}")
    if cfg.max_iters < 1:
        raise RispError(f"--max-iters must be >= 1, got {cfg.max_iters}")
    if cfg.effects is not None and not cfg.effects:  # "--effects ," ran the base model alone without a word
        raise RispError("--effects names no effect; leave it out to try the whole library")
    if cfg.floor_offset != "auto" and not (isinstance(cfg.floor_offset, (int, float))
                                           and math.isfinite(cfg.floor_offset)):
        raise RispError(f"--floor-offset must be 'auto' or a finite number of metres, got {cfg.floor_offset!r}")
    if cfg.max_segments < 1 or (cfg.rollout_horizon is not None and cfg.rollout_horizon < 1):
        raise RispError("--max-segments and --rollout-horizon must be >= 1")
    from risp_data.threads import torch_threads

    # nothing below draws from torch's global RNG; seeded in a fork so that stray use is reproducible
    # and the caller's generator is left as it was
    with torch_threads(1), torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(cfg.seed))
        return _diagnose(cfg)


def check_out(out: str | None) -> None:
    """Fail before hours of fitting when the report could not be put in place (one line).  The report replaces
    ``out`` as a whole (:func:`report.write_report`), so ``out`` must be new, empty or an earlier report: a folder
    holding anything else is refused rather than deleted.  A symlink, a mount point or a folder in an unwritable one
    is written into file by file instead (:func:`report.replaced_whole`): it must be writable itself."""
    if out is None:
        return
    from risp_data.atomic import TEMP_PREFIX, probe_writable

    from .report import REPORT_FILES, replaced_whole

    path = Path(out)
    try:
        whole = replaced_whole(path)
        if path.exists():
            if not path.is_dir():
                raise RispError(f"{path}: --out exists and is not a folder")
            if whole and Path.cwd().resolve().is_relative_to(path.resolve()):
                raise RispError(f"{path}: --out is the current folder (or holds it); the report replaces its "
                                f"folder as a whole: name a new one, e.g. --out report/")
            other = sorted(n for n in os.listdir(path) if n not in REPORT_FILES and not n.startswith(TEMP_PREFIX))
            if other:  # replaced whole they would be deleted; written into, their names could be the plots'
                raise RispError(f"{path}: --out holds files that are not a diagnose report ({other[0]}"
                                f"{', …' if len(other) > 1 else ''}); name a new or empty folder")
        # written into file by file (a symlink, a mount point), or a sibling folder renamed over it
        probe_writable(path if path.exists() and not whole else path.absolute().parent)
    except OSError as e:
        raise RispError(f"{e.filename or path}: cannot write the report there ({e.strerror})") from None


def _diagnose(cfg: DiagnoseConfig) -> dict:
    t0 = time.perf_counter()
    overrides = {"side": cfg.side, "mass": cfg.mass} if cfg.env == "cube" else {}
    trajs = load_measured(cfg.data, cfg.env, overrides=overrides, limit=cfg.limit)
    if cfg.horizon < 1:
        raise RispError(f"--horizon must be at least 1, got {cfg.horizon}")
    cands.check_supported(cfg.env, trajs[0].sidecar)
    fit_trajs, held_trajs, split = split_trajectories(trajs, cfg.held_out, cfg.seed)
    # the floor from the fitting part's resting frames only ("everything is fitted on the fitting part"), applied
    # to both parts
    shifted, floor = calibrate_floor(fit_trajs + held_trajs, cfg.floor_offset, estimate_from=fit_trajs)
    fit_trajs, held_trajs = shifted[:len(fit_trajs)], shifted[len(fit_trajs):]

    library = cands.effect_names(cfg.env, trajs[0].sidecar)
    if cfg.effects is not None:
        unknown = [e for e in cfg.effects if e not in library]
        if unknown:
            raise RispError(f"unknown effect(s) {', '.join(unknown)} for {cfg.env}; choose from: {', '.join(library)}")
        library = tuple(cfg.effects)

    base_model, _ = cands.build_model(cfg.env, (), fit_trajs[0].sidecar, fit_trajs[0].dt)
    sc = fit_trajs[0].sidecar
    noise, phi, noise_info = noise_model(base_model.sim, fit_trajs, declared=sc.get("measurement_noise"),
                                         declared_phi=float(sc.get("measurement_noise_correlation", 0.0)))
    check_out(cfg.out)  # after the input checks (a bad input leaves no folder), before the long fits

    n_total = 1 + len(library) + len(cands.pair_candidates(list(library), cfg.pairs_top))
    bar = tqdm(total=n_total, desc="diagnose: fitting models", disable=not cfg.progress, leave=False)
    evaluated: dict[str, Evaluated] = {}

    def run(effects):
        ev = evaluate_model(effects, fit_trajs, held_trajs, cfg, noise, bar, phi)
        evaluated[ev.fit.model.name] = ev
        bar.update(1)
        return ev

    base = run(())
    singles = [run((e,)) for e in library]
    ranked_singles = [s.score.name for s in sorted(singles, key=lambda ev: ev.score.bic)]
    pairs = [run(p) for p in cands.pair_candidates(ranked_singles, cfg.pairs_top)]
    bar.close()

    decision = decide(base.score, [s.score for s in singles], [p.score for p in pairs])
    chosen = evaluated[decision.selected.name]
    # no confident wrong names: the selected model's held-out residual must not depend on a regressor
    dependence = residual_dependence(chosen.fit, chosen.obs, chosen.sigma, held_trajs, cfg.horizon, chosen.k, cfg.seed,
                                     phi=max(phi.values(), default=0.0))
    decision = check_dependence(decision, dependence)
    decision, runner_up = runner_up_note(decision, [ev.score for ev in evaluated.values()])
    estimated_by = next((tr.sidecar.get("estimated_by") for tr in trajs if tr.sidecar.get("estimated_by")), None)
    decision = estimate_note(decision, estimated_by, noise_info)
    fixed = dict(zip(base.fit.model.sim.param_names, (float(v) for v in base.fit.model.base)))
    decision = estimate_force_note(decision, estimated_by, chosen.fit.values, fixed.get("mass"))
    ext_for_gain = chosen if decision.selected.name != "base" else (
        evaluated[decision.best_candidate.name] if decision.best_candidate is not None else base)

    base_err = errors(base, held_trajs, cfg)
    ext_err = errors(ext_for_gain, held_trajs, cfg)
    ranking = [_score_row(ev.score, base.score) for ev in sorted(evaluated.values(), key=lambda ev: ev.score.bic)]

    def params_of(ev: Evaluated) -> dict:
        sim = ev.fit.model.sim
        # the base parameters' units (fitted ones, e.g. k_f of a normalised-command log, print with them too)
        units = dict(zip(sim.spec.base_param_names, sim.spec.base_param_units or ()))
        for e in ev.fit.model.effects:
            eff = sim.spec.available_effects[e]
            for p, u in zip(eff.param_names, eff.units or ("",) * len(eff.param_names)):
                units[f"{e}.{p}"] = u
        return {n: {"value": v, "std": ev.fit.stds.get(n, float("nan")), "unit": units.get(n, ""),
                    **bound_flag(ev.fit.model, n, v)}
                for n, v in ev.fit.values.items()}

    report = {
        "env": cfg.env,
        "cause": decision.cause,
        "reason": decision.reason,
        "selected_model": decision.selected.name,
        "compared_model": ext_for_gain.fit.model.name,
        "parameters": params_of(chosen) if decision.cause not in ("none",) else {},
        "candidate_parameters": {name: params_of(ev) for name, ev in evaluated.items() if ev.fit.model.effects},
        "fixed_parameters": fixed,
        "ranking": ranking,
        "residual_dependence": [d.as_dict() for d in dependence[:10]],
        "runner_up": runner_up,
        "base_error": base_err,
        "extended_error": ext_err,
        "gain": gain(base_err, ext_err),
        "noise": noise,
        "noise_model": noise_info,
        "thresholds": {"delta_bic_min": 10.0, "min_rss_reduction": 0.05, "noise_floor_ratio_max": RHO_MAX},
        "split": split,
        "seed": int(cfg.seed),
        "data": {"files": [tr.path for tr in trajs], "samples": int(sum(tr.n for tr in trajs)),
                 "sample_interval_s": float(trajs[0].dt), "sidecar": trajs[0].sidecar.source,
                 "velocities_estimated": bool(any(tr.vel_estimated for tr in trajs if tr.vel is not None)),
                 "angular_velocities_estimated": bool(any(tr.omega_estimated for tr in trajs)),
                 "floor_calibration": floor},
        "fit": {"horizon_samples": cfg.horizon, "substeps_per_sample": base.k, "sim_dt_s": base.fit.model.sim.dt,
                "iterations": {n: ev.fit.iterations for n, ev in evaluated.items()}},
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()},
        "runtime_s": None,
    }
    report["runtime_s"] = time.perf_counter() - t0
    if cfg.out is not None:
        from .report import write_report

        try:
            write_report(report, cfg, evaluated, base, ext_for_gain, fit_trajs, held_trajs)
        except OSError as e:  # disk full, permissions: nothing half-written (atomic writes), one line
            raise RispError(f"{e.filename or cfg.out}: cannot write the report ({e.strerror})") from None
    return report
