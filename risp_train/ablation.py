"""The paper's data-efficiency ablation, and the regularizer comparison on target-domain shards.

    risp-train ablation --env cube --out runs/ablation --preset cpu

For every pool size P in ``--pools`` (default: 1, 10 and ``per-sample``) a training set of ``--n-train``
samples is rendered whose rendering configurations (ψ and the non-differentiable aux: light direction,
floor texture, …) are drawn from a fixed pool of P configurations (sample i uses pool entry i mod P;
``per-sample``: a new configuration per sample, i.e. a plain ``risp-data render`` job).  States and
render seeds are those of the plain job with the same seed.  A network is trained on each set with
every regularizer in ``--regs`` and evaluated (evaluate.py: mean ± std of the per-image state error) on

* ``unseen``: train-domain shards with configurations drawn per sample from another seed (so none of
  them is in any pool), and
* ``target``: target-domain shards (another look: area light, sky, glossy materials, textures).

Outputs: ``ablation.json`` (all numbers and settings), ``ablation.md`` (tables), ``ablation.png``
(error vs pool size per regularizer, both evaluation sets).  Finished renders and trainings are kept
and skipped when the command is run again.

The pooled training sets are rendered here with risp_data's Renderer and shard writer (``risp-data
render`` has no option for a fixed configuration pool); their manifest carries a ``psi_pool`` record.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass

import numpy as np

from risp_data.errors import RispError

from .regularizers import REGULARIZERS
from risp_data.atomic import write_text_atomic

PER_SAMPLE = "per-sample"


@dataclass(frozen=True)
class AblationConfig:
    env: str
    out: str
    pools: tuple[str, ...] = ("1", "10", PER_SAMPLE)
    regs: tuple[str, ...] = REGULARIZERS
    n_train: int = 512
    n_eval: int = 128
    resolution: int = 64
    spp: int = 8
    shard_size: int = 64
    seed: int = 0
    preset: str = "cpu"
    epochs: int | None = None
    batch_size: int | None = None
    width: int | None = None
    lr: float | None = None
    gamma: float | None = None
    workers: int = 2
    target: bool = True  # also evaluate on target-domain shards


def _validate(cfg: AblationConfig) -> None:
    from risp_data.envs import get_environment

    get_environment(cfg.env)
    for option, values in (("--pools", cfg.pools), ("--regs", cfg.regs)):
        if not values:
            raise RispError(f"{option} is empty: name at least one")
        if len(set(values)) != len(values):
            raise RispError(f"{option} names an entry twice: {','.join(values)}")
    if cfg.gamma is not None and not (math.isfinite(cfg.gamma) and cfg.gamma >= 0):
        raise RispError(f"--gamma must be a finite number >= 0, got {cfg.gamma}")
    if cfg.batch_size is not None and cfg.batch_size > cfg.n_train:
        raise RispError(f"--batch-size {cfg.batch_size} is larger than --n-train {cfg.n_train}")
    for p in cfg.pools:
        if p != PER_SAMPLE and not (p.isdigit() and int(p) >= 1):
            raise RispError(f"--pools entries must be positive integers or {PER_SAMPLE!r}, got {p!r}")
    for r in cfg.regs:
        if r not in REGULARIZERS:
            raise RispError(f"unknown regularizer {r!r} in --regs; choose from: {', '.join(REGULARIZERS)}")
    if cfg.n_train < 1 or cfg.n_eval < 1:
        raise RispError("--n-train and --n-eval must be >= 1")
    if cfg.seed < 0 or (cfg.batch_size is not None and cfg.batch_size < 1):
        raise RispError("--seed must be >= 0 and --batch-size >= 1")


def _job(cfg: AblationConfig, out: str, n: int, domain: str, seed: int, jacobian: bool):
    from risp_data.generate import RenderJob

    return RenderJob(env=cfg.env, n=n, out=out, domain=domain, formats=("wds",), resolution=cfg.resolution,
                     spp=cfg.spp, seed=seed, workers=1, shard_size=min(cfg.shard_size, n), jacobian=jacobian)


def config_pool(env: str, size: int, seed: int) -> list:
    """``size`` training-domain rendering configurations drawn from SeedSequence(seed, size)."""
    from risp_data.psi import sample_rendering

    rng = np.random.default_rng(np.random.SeedSequence([seed, size, 0x9001]))
    return [sample_rendering(env, "train", rng) for _ in range(size)]


def pool_record(pool: list) -> dict:
    """The manifest's ``psi_pool``: every look of the pool (ψ and aux), so that risp-data verify re-renders a sample
    with its own look and risp-data refuses to resume the folder without it."""
    from risp_data.generate import jsonable

    return {"size": len(pool), "rule": "sample i uses pool[i % size]",
            "psi": [np.asarray(c.psi).tolist() for c in pool], "aux": [jsonable(c.aux) for c in pool]}


def render_pooled(job, pool: list, progress: bool = True) -> str:
    """Render ``job`` with sample i's configuration = pool[i mod P] (states/seeds as in the plain job)."""
    from risp_data.generate import check_folder, folder_lock, validate_job
    from risp_data.mitsuba_setup import init_mitsuba

    validate_job(job)
    variant = init_mitsuba(job.variant)
    record = pool_record(pool)
    check_folder(job, variant, record)  # refuses another job's or another pool's folder
    os.makedirs(job.out, exist_ok=True)
    with folder_lock(job.out):
        return _render_pooled_locked(job, pool, record, variant, progress)


def _render_pooled_locked(job, pool: list, record: dict, variant: str, progress: bool) -> str:
    from tqdm.auto import tqdm

    from risp_data.envs import get_environment
    from risp_data.generate import make_renderer, prepare_folder, render_sample
    from risp_data.shards.manifest import save_manifest
    from risp_data.shards.writer import write_shard
    from risp_data.threads import available_cpus, drjit_threads, torch_threads

    manifest = prepare_folder(job, variant, psi_pool=record)
    if manifest.get("psi_pool") != record:  # on disk before the first shard's marker: a kill in between leaves a
        manifest["psi_pool"] = record       # folder the pool resumes (and an older record, of the same looks
        save_manifest(job.out, manifest)    # without their aux, gets them)
    done = {r["index"] for r in manifest["shards"]}
    todo = [i for i in range(job.num_shards) if i not in done]
    if not todo:
        return job.out
    env = get_environment(job.env)
    total = sum(job.shard_range(i)[1] - job.shard_range(i)[0] for i in todo)
    # (Mitsuba was set up by render_pooled.) As risp-data's in-process render: Dr.Jit on the CPUs this process may use (not its default of every core of
    # the machine), one torch thread; the caller's counts come back afterwards
    with torch_threads(1), drjit_threads(available_cpus()), \
            tqdm(total=total, unit="sample", desc=f"render pool={len(pool)}", disable=not progress) as bar:
        renderer = make_renderer(job)
        for shard in todo:
            samples = []
            for i in range(*job.shard_range(shard)):
                # risp-data's own sample renderer (its non-finite checks, its metadata) with the pool's look
                sample = render_sample(renderer, env, job, i, config=pool[i % len(pool)])
                sample.meta["psi_pool_index"] = i % len(pool)
                samples.append(sample)
                bar.update(1)
            rec = write_shard(job.out, job.formats, shard, samples)
            manifest["shards"] = [r for r in manifest["shards"] if r["index"] != shard] + [rec]
            save_manifest(job.out, manifest)
    return job.out


def run_ablation(cfg: AblationConfig, progress: bool = True) -> dict:
    """Render, train and evaluate every (pool, regularizer) pair; write JSON, markdown and the figure."""
    from risp_data.generate import run_job

    from .config import make_config
    from .evaluate import EvalConfig, evaluate
    from .plots import plot_ablation
    from .train import MODEL, fit

    _validate(cfg)
    os.makedirs(cfg.out, exist_ok=True)
    quiet = (lambda *_: None)
    data = os.path.join(cfg.out, "shards")
    # evaluation sets: configurations never in any pool (another seed), and the target domain
    eval_sets = {"unseen": os.path.join(data, "eval-unseen")}
    run_job(_job(cfg, eval_sets["unseen"], cfg.n_eval, "train", cfg.seed + 1, False), progress=progress, log=quiet)
    if cfg.target:
        run_job(_job(cfg, os.path.join(data, "eval-target"), cfg.n_eval, "target", cfg.seed + 2, False),
                progress=progress, log=quiet)
        eval_sets["target"] = os.path.join(data, "eval-target")
    results = []
    for pool in cfg.pools:
        train_dir = os.path.join(data, f"train-pool-{pool}")
        job = _job(cfg, train_dir, cfg.n_train, "train", cfg.seed, True)
        if pool == PER_SAMPLE:
            run_job(job, progress=progress, log=quiet)
        else:
            render_pooled(job, config_pool(cfg.env, int(pool), cfg.seed), progress=progress)
        for reg in cfg.regs:
            run_dir = os.path.join(cfg.out, "runs", f"pool-{pool}-{reg}")
            model = os.path.join(run_dir, MODEL)
            tcfg = make_config(train_dir, run_dir, preset=cfg.preset, reg=reg, gamma=None if reg == "none" else cfg.gamma,
                               epochs=cfg.epochs,
                               batch_size=cfg.batch_size, width=cfg.width, lr=cfg.lr, seed=cfg.seed,
                               workers=cfg.workers)
            if os.path.exists(model):  # reused only when it was trained as asked now
                _check_reused_run(run_dir, tcfg, cfg.env)
            else:
                fit(tcfg, resume=True, progress=progress)
            row = {"pool": pool, "reg": reg, "model": model}
            for name, folder in eval_sets.items():
                # evaluated again at every re-run: its own results, replaced (a reused run's may predate a fix)
                res = evaluate(EvalConfig(model=model, shards=folder, seed=cfg.seed, overwrite=True,
                                          out=os.path.join(run_dir, f"eval-{name}")), progress=False)
                r = res["results"]
                row[name] = {"mean": r["model"]["mean"], "std": r["model"]["std"]}
                row[f"{name}_baselines"] = {k: r[k] for k in ("average", "random")}
            results.append(row)
    summary = {"config": {**asdict(cfg), "pools": list(cfg.pools), "regs": list(cfg.regs)}, "metric": "l1",
               "eval_sets": eval_sets, "results": results}
    _write(os.path.join(cfg.out, "ablation.json"), json.dumps(summary, indent=1, sort_keys=True) + "\n")
    _write(os.path.join(cfg.out, "ablation.md"), ablation_markdown(summary) + "\n")
    plot_ablation(results, os.path.join(cfg.out, "ablation.png"), "l1", list(eval_sets), seed=cfg.seed)
    return summary


def _check_reused_run(run_dir: str, tcfg, env: str) -> None:
    """A finished run of an earlier ablation in this --out is reused only if its training options are today's
    (a rerun with another --epochs used to report the old networks under the new options)."""
    from .train import option_changes

    try:
        with open(os.path.join(run_dir, "config.json")) as f:
            stored = json.load(f)
        changes = option_changes(stored["config"], tcfg, env, used=stored)
    except (OSError, ValueError, KeyError) as e:
        raise RispError(f"{run_dir}: cannot read the finished run's config.json ({type(e).__name__}); remove the "
                        "run folder to train it again") from None
    if changes:
        raise RispError(f"{run_dir} was trained with other options than this ablation asks for "
                        f"({', '.join(changes)}); choose another --out, or remove that run folder to train it again")


def ablation_markdown(summary: dict) -> str:
    sets = list(summary["eval_sets"])
    pools = [("a new rendering configuration per sample" if p == PER_SAMPLE else f"{p} rendering configuration"
              + ("s" if p != "1" else "")) for p in summary["config"]["pools"]]
    lines = [f"Per-image L1 state error (mean ± std) of {summary['config']['env']} networks trained with "
             f"{', '.join(pools[:-1]) + ' or ' + pools[-1] if len(pools) > 1 else pools[0]}", "",
             "| configurations | regularizer | " + " | ".join(f"{s} (mean ± std)" for s in sets) + " |",
             "|---|---|" + "---:|" * len(sets)]
    for r in summary["results"]:
        cells = " | ".join(f"{r[s]['mean']:.4f} ± {r[s]['std']:.4f}" for s in sets)
        lines.append(f"| {r['pool']} | {r['reg']} | {cells} |")
    if summary["results"]:
        first = summary["results"][0]
        for name in ("average", "random"):
            cells = " | ".join(f"{first[f'{s}_baselines'][name]['mean']:.4f} ± {first[f'{s}_baselines'][name]['std']:.4f}"
                               for s in sets)
            lines.append(f"| baseline | {name} | {cells} |")
    return "\n".join(lines)


def _write(path: str, text: str) -> None:
    write_text_atomic(path, text)
