"""State-estimation evaluation (``risp-train eval MODEL SHARDS``): the paper's metric and two baselines.

For every image b of the evaluation shards (typically another domain, or unseen ψ) the per-image state
error is

    e_b = (1/S) Σ_i |Δ_bi|        (``l1``, default)      or      e_b = ‖Δ_b‖₂     (``l2``)

with Δ_b = ŝ_b − s_b, where angular state components (yaw, pitch, roll) are wrapped to (−π, π].
We report the mean and the standard deviation of e_b over the images, as the paper's state-estimation
table does, and the per-dimension mean absolute error, for

* ``model``:   ŝ_b = the trained predictor on image b;
* ``average``: ŝ_b = the training mean, i.e. target_to_state(μ) of the stored target mean μ (for sin/cos
  pairs that is the circular mean), the same for every image;
* ``random``:  ŝ_b drawn from the environment's state sampler (seeded by ``--seed``).

Per state group, in physical units (:func:`group_errors`; mean ± std over the images and the count):

* ``position`` [m] (quadrotor, cube):  ‖p̂_b − p_b‖₂, the Euclidean distance of the centres;
* ``attitude`` [deg] (quadrotor, cube): the geodesic angle between the orientations,
  θ_b = arccos((tr(R̂_bᵀ R_b) − 1) / 2), R = Rz(yaw) Ry(pitch) Rx(roll) — the angle of the one rotation
  that takes the prediction to the truth, free of Euler-angle wrap-around and gimbal effects;
* ``joints`` [rad] (hand):  (1/13) Σ_i |θ̂_bi − θ_bi|, the mean joint-angle error;
* ``sensors`` [m] (rod):    (1/10) Σ_i |ẑ_bi − z_bi|, the mean sensor-height error.

``risp-train eval`` also writes ``<prefix>_scatter.png``: predicted vs true, one panel per state entry.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass

import numpy as np
import torch

from risp_data.errors import RispError
from risp_data.shards.manifest import package_versions, risp_commit

from .checkpoint import check_compatible, read_checkpoint
from .data import iter_batches, manifest_hash, open_shards
from .predictor import predictor_from_checkpoint
from risp_data.atomic import check_writable, write_text_atomic

METRICS = ("l1", "l2")
ANGLE_NAMES = ("yaw", "pitch", "roll")


@dataclass(frozen=True)
class EvalConfig:
    model: str
    shards: str
    metric: str = "l1"
    seed: int = 0  # seeds the random baseline
    batch_size: int = 32
    limit: int | None = None  # evaluate at most this many images
    format: str = "auto"
    out: str | None = None  # path prefix of the .json / .md files; None → <model dir>/eval-<shards name>
    overwrite: bool = False  # replace the results an earlier evaluation wrote under the prefix (else refused)


def state_differences(pred: np.ndarray, true: np.ndarray, state_names) -> np.ndarray:
    """Δ = pred − true (N, S), angular components wrapped to (−π, π]."""
    d = np.asarray(pred, np.float64) - np.asarray(true, np.float64)
    for i, name in enumerate(state_names):
        if name in ANGLE_NAMES:
            d[:, i] = -np.remainder(-d[:, i] + np.pi, 2 * np.pi) + np.pi
    return d


def per_image_error(diff: np.ndarray, metric: str) -> np.ndarray:
    if metric == "l1":
        return np.abs(diff).mean(axis=1)
    if metric == "l2":
        return np.sqrt((diff * diff).sum(axis=1))
    raise RispError(f"unknown --metric {metric!r}; choose one of: {', '.join(METRICS)}")


def summarize(diff: np.ndarray, metric: str) -> dict:
    e = per_image_error(diff, metric)
    return {"mean": float(e.mean()), "std": float(e.std()), "per_dim_mae": np.abs(diff).mean(axis=0).tolist()}


# state groups per environment: name -> (unit, state indices); see group_errors for the formulas
STATE_GROUPS = {
    "quadrotor": {"position": ("m", (0, 1, 2)), "attitude": ("deg", (3, 4, 5))},
    "cube": {"position": ("m", (0, 1, 2)), "attitude": ("deg", (3, 4, 5))},
    "hand": {"joints": ("rad", tuple(range(13)))},
    "rod": {"sensors": ("m", tuple(range(10)))},
}


def geodesic_angle_deg(pred_euler: np.ndarray, true_euler: np.ndarray) -> np.ndarray:
    """θ = arccos((tr(R̂ᵀR) − 1)/2) in degrees for (N, 3) yaw, pitch, roll arrays → (N,)."""
    from risp_data.envs.rotations import euler_to_matrix

    def matrices(e):
        e = torch.as_tensor(np.asarray(e, np.float64))
        return euler_to_matrix(e[:, 0], e[:, 1], e[:, 2]).numpy()

    Rp, Rt = matrices(pred_euler), matrices(true_euler)
    cos = (np.einsum("nij,nij->n", Rp, Rt) - 1.0) / 2.0  # tr(R̂ᵀR) = Σ_ij R̂_ij R_ij
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def group_errors(env_name: str, pred: np.ndarray, true: np.ndarray) -> dict[str, np.ndarray]:
    """Per-image errors per state group (module docstring): {group: (N,) array} in the group's unit."""
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    out = {}
    for group, (_, idx) in STATE_GROUPS[env_name].items():
        idx = list(idx)
        if group == "position":
            out[group] = np.linalg.norm(pred[:, idx] - true[:, idx], axis=1)
        elif group == "attitude":
            out[group] = geodesic_angle_deg(pred[:, idx], true[:, idx])
        else:  # joints, sensors: mean absolute error over the entries
            out[group] = np.abs(pred[:, idx] - true[:, idx]).mean(axis=1)
    return out


def summarize_groups(env_name: str, pred: np.ndarray, true: np.ndarray) -> dict:
    """{group: {"mean", "std", "n", "unit"}} of :func:`group_errors`."""
    units = {g: u for g, (u, _) in STATE_GROUPS[env_name].items()}
    return {g: {"mean": float(e.mean()), "std": float(e.std()), "n": int(e.size), "unit": units[g]}
            for g, e in group_errors(env_name, pred, true).items()}


def evaluate(cfg: EvalConfig, progress: bool = True) -> dict:
    """Evaluate the model and the baselines on ``cfg.shards``; writes JSON + markdown, returns the dict."""
    from tqdm.auto import tqdm

    from risp_data.envs import get_environment

    if cfg.metric not in METRICS:
        raise RispError(f"unknown --metric {cfg.metric!r}; choose one of: {', '.join(METRICS)}")
    if cfg.seed < 0 or cfg.batch_size < 1 or (cfg.limit is not None and cfg.limit < 1):
        raise RispError("--seed must be >= 0, --batch-size >= 1 and --limit >= 1")
    ckpt, model_sha = read_checkpoint(cfg.model)  # the hash of the bytes evaluated (a fit may replace the file)
    shards = open_shards(cfg.shards, cfg.format)
    prefix = _out_prefix(cfg)
    check_writable(os.path.dirname(os.path.abspath(prefix)), "--out folder")  # before the evaluation, not after
    if not cfg.overwrite:
        _refuse_earlier_results(prefix)
    check_compatible(ckpt, cfg.model, env=shards.env, state_names=shards.state_names, resolution=shards.resolution)
    env = get_environment(shards.env)
    predictor = predictor_from_checkpoint(ckpt, cfg.model)
    n_total = shards.num_samples if cfg.limit is None else min(cfg.limit, shards.num_samples)
    preds, trues = [], []
    with torch.no_grad(), tqdm(total=n_total, unit="img", desc="eval", disable=not progress) as bar:
        for batch in iter_batches(shards, cfg.batch_size, state_dim=env.state_dim, limit=cfg.limit):
            states, _ = predictor.predict(batch["image"])
            preds.append(states.double().numpy())
            trues.append(batch["state"].numpy())
            bar.update(len(batch["key"]))
    if not trues:
        raise RispError(f"shard folder {cfg.shards} holds no samples to evaluate")
    pred, true = np.concatenate(preds), np.concatenate(trues)
    n = true.shape[0]
    mean_target = torch.tensor(predictor.normalization.target_mean, dtype=torch.float64)
    avg_state = env.target_to_state(mean_target[None]).numpy()
    rand_state = np.asarray(env.sample_states(np.random.default_rng(np.random.SeedSequence(cfg.seed)), n), np.float64)
    names = list(env.state_names)
    estimates = {"model": pred, "average": np.repeat(avg_state, n, 0), "random": rand_state}
    result = {
        "env": shards.env, "shards": os.path.abspath(cfg.shards), "domain": shards.manifest.get("domain"),
        "manifest_hash": manifest_hash(shards.manifest), "model": os.path.abspath(cfg.model),
        "model_sha256": model_sha, "versions": {**package_versions(), "risp_commit": risp_commit()},
        "train_manifest_hash": ckpt.get("manifest_hash"), "reg": ckpt.get("config", {}).get("reg"),
        "metric": cfg.metric, "n": n, "seed": cfg.seed, "state_names": names,
        "results": {k: summarize(state_differences(v, true, names), cfg.metric) for k, v in estimates.items()},
        "groups": {k: summarize_groups(shards.env, v, true) for k, v in estimates.items()},
        "config": asdict(cfg),
    }
    _write_results(result, pred, true, prefix, cfg)
    result["files"] = [prefix + ".json", prefix + ".md", prefix + "_scatter.png"]
    return result


#: what an evaluation writes under its prefix; published in this order, the JSON (the record) last: it is there only
#: with the other two (risp_data.atomic.publish_files)
RESULT_SUFFIXES = ("_scatter.png", ".md", ".json")


def _refuse_earlier_results(prefix: str) -> None:
    """One line naming an earlier evaluation's file under ``prefix``: replacing it needs --overwrite."""
    found = [prefix + s for s in RESULT_SUFFIXES[::-1] if os.path.lexists(prefix + s)]
    if found:
        raise RispError(f"{found[0]} already exists (an earlier evaluation's result); pass --overwrite to replace "
                        "its .json, .md and _scatter.png, or choose another --out")


def _write_results(result: dict, pred: np.ndarray, true: np.ndarray, prefix: str, cfg: EvalConfig) -> None:
    """The JSON, the markdown table and the scatter plot, written into a temporary folder beside them and then
    published as one set: a killed evaluation leaves the earlier set or the new one (or part of one), never a mix."""
    import shutil

    from risp_data.atomic import publish_files, temp_folder

    from .plots import plot_predicted_vs_true

    folder, base = os.path.split(os.path.abspath(prefix))
    os.makedirs(folder, exist_ok=True)
    tmp = temp_folder(folder)
    try:
        staged = os.path.join(tmp, base)
        write_text_atomic(staged + ".json", json.dumps(result, indent=1, sort_keys=True) + "\n")
        write_text_atomic(staged + ".md", markdown_table(result) + "\n")
        names = list(result["state_names"])
        units = [None] * len(names)
        for unit, idx in STATE_GROUPS.get(result["env"], {}).values():
            for i in idx:
                units[i] = unit
        plot_predicted_vs_true(pred, true, names, staged + "_scatter.png",
                               title=f"{result['env']}, {result['domain']} domain, {result['n']} images", units=units,
                               seed=cfg.seed)
        if not cfg.overwrite:  # another evaluation may have written there since the start
            _refuse_earlier_results(prefix)
        publish_files(tmp, folder, [base + s for s in RESULT_SUFFIXES])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _out_prefix(cfg: EvalConfig) -> str:
    """The path prefix of the result files: ``--out``, or ``eval-<shards name>`` beside the model or in ``--out``'s
    folder."""
    name = "eval-" + os.path.basename(os.path.normpath(cfg.shards))
    prefix = cfg.out or os.path.join(os.path.dirname(os.path.abspath(cfg.model)), name)
    if cfg.out and (cfg.out.endswith(("/", os.sep)) or os.path.isdir(cfg.out)):  # a folder: the default name in it
        prefix = os.path.join(cfg.out, name)
    return prefix


def markdown_table(result: dict) -> str:
    """One row per method: each state group's error (mean ± std, unit) and the paper's per-image L1/L2."""
    m = result["metric"].upper()
    groups = result.get("groups", {})
    names = list(next(iter(groups.values()), {}))
    head = [f"{g} [{groups['model'][g]['unit']}]" for g in names] + [f"paper {m} (all entries)"]
    lines = [f"State estimation on `{result['shards']}` ({result['env']}, domain {result['domain']}, "
             f"n = {result['n']} images; mean ± std over images; `random` drawn with seed {result.get('seed')})", "",
             "| method | " + " | ".join(head) + " |", "|---|" + "---:|" * len(head)]
    for method, r in result["results"].items():
        cells = [_pm(groups[method][g]["mean"], groups[method][g]["std"], groups[method][g]["unit"])
                 for g in names] + [_pm(r["mean"], r["std"], "")]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _pm(mean: float, std: float, unit: str) -> str:
    """'mean ± std' with digits that suit the unit (degrees: 1 decimal, else 4 significant-ish)."""
    if unit == "deg":
        return f"{mean:.1f} ± {std:.1f}"
    return f"{mean:.4f} ± {std:.4f}"
