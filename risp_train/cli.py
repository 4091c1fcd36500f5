"""``risp-train``: fit, eval and ablation (thin: click options → frozen config → a function).

    risp-train fit SHARDS [--out runs/NAME] [--reg none|surrogate|exact|stochastic] [--preset paper|cpu] ...
    risp-train eval MODEL SHARDS [--metric l1|l2] [--out PREFIX] [--overwrite]
    risp-train ablation --env cube --out runs/ablation ...
    torchrun --nproc-per-node 2 -m risp_train fit SHARDS --out runs/NAME ...

docs/cli-train.md lists every option.
"""

from __future__ import annotations

import json
import os

import click

from risp_data.cli_util import RispGroup, run_cli
from risp_data.envs import ENV_NAMES
from risp_data.errors import RispError

from .defaults import DEFAULT_REG, PRESET_CHOICES, REG_CHOICES


@click.group(cls=RispGroup)
@click.version_option(package_name="risp", message="%(prog)s (risp) %(version)s")
def cli():
    """Train and evaluate the RISP state predictor on rendered shards."""


@cli.command()
@click.argument("shards", type=click.Path())
@click.option("--out", default=None, type=click.Path(file_okay=False), help="Run folder (checkpoints, logs, plots) [runs/DATASET-REG-sSEED].")
@click.option("--reg", type=click.Choice(REG_CHOICES), default=DEFAULT_REG, show_default=True, help="Regularizer (docs/training.md).")
@click.option("--gamma", type=float, default=None, help="Final weight γ of the calibrated regularizer (dimensionless) [per environment, docs/training.md].")
@click.option("--gamma-ramp", type=float, default=0.5, show_default=True, help="γ ramps linearly from 0 over this fraction of the steps after its start.")
@click.option("--gamma-start", type=float, default=None, help="γ is 0 before this fraction of all steps, then ramps [per environment: quadrotor and cube 0.5, else 0].")
@click.option("--preset", type=click.Choice(PRESET_CHOICES), default=None, help="paper (ResNet-18 w64, 100 epochs, lr 1e-2) or cpu (w16, 20 epochs, lr 3e-3) [paper with a CUDA GPU, else cpu].")
@click.option("--epochs", type=int, default=None, help="Epochs [preset].")
@click.option("--batch-size", type=int, default=None, help="Images per step and process [preset: 16].")
@click.option("--lr", type=float, default=None, help="Adam learning rate, cosine-decayed to 0 [preset].")
@click.option("--weight-decay", type=float, default=None, help="Adam weight decay [preset: 1e-6].")
@click.option("--width", type=int, default=None, help="ResNet-18 first-stage channels [preset].")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of weights, data order and the stochastic regularizer.")
@click.option("--workers", type=int, default=2, show_default=True, help="DataLoader worker processes per rank.")
@click.option("--threads", type=int, default=0, show_default=True, help="torch threads per rank (0: the CPUs left after --workers; 1 on a shared 2-core machine).")
@click.option("--device", default="auto", show_default=True, help="auto (CUDA when torch sees a GPU), cpu, cuda or cuda:N.")
@click.option("--format", "fmt", default="auto", show_default=True, help="Read wds or zarr shards (auto: wds if present).")
@click.option("--cache", default="auto", show_default=True, help="memory: decode the data once and train from memory; stream: decode every epoch; auto: memory when it needs at most half of the available memory.")
@click.option("--checkpoint-every", type=int, default=0, show_default=True, help="Also checkpoint every N steps (0: epoch ends only).")
@click.option("--rank-check", default="stop", show_default=True, help="torchrun ranks whose weights differ at an epoch end: stop, or resync (every rank takes rank 0's weights; for nodes with different CPUs).")
@click.option("--val", type=click.Path(), default=None, help="Held-out shard folder evaluated at each epoch end.")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last checkpoint.")
@click.option("--overwrite", is_flag=True, help="Replace the model/checkpoint a run folder already holds.")
@click.option("--allow-incomplete", is_flag=True, help="Train on an unfinished shard folder's complete shards.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def fit(shards, out, reg, gamma, gamma_ramp, gamma_start, preset, epochs, batch_size, lr, weight_decay, width, seed, workers,
        threads, device, fmt, cache, checkpoint_every, rank_check, val, resume, overwrite, allow_incomplete, quiet):
    """Train on the shard folder SHARDS (decoded once into memory where it fits, else streamed; resolution from
    its manifest).

    SHARDS may also be a folder holding data sets (e.g. shards/ after `risp-data render`): the one data set in
    it, or its one train-domain set with Jacobians, is used; otherwise the error lists what it holds."""
    from .config import default_preset, make_config
    from .train import fit as run_fit

    rank0 = int(os.environ.get("RANK", "0")) == 0
    from click.core import ParameterSource

    ramp_given = click.get_current_context().get_parameter_source("gamma_ramp") == ParameterSource.COMMANDLINE
    if reg == "none" and (gamma is not None or gamma_start is not None or ramp_given):  # would be ignored silently
        raise RispError("--gamma, --gamma-start and --gamma-ramp set the regularizer's weight; --reg none trains "
                        "without one (leave them out, or choose a regularizer)")
    shards = find_dataset(shards, need_jacobian=reg != "none")
    why = "--preset"
    if preset is None:
        preset = default_preset()
        why = "default: " + ("a CUDA GPU is present" if preset == "paper" else "no CUDA GPU")
    if out is None:
        out = os.path.join("runs", f"{os.path.basename(os.path.normpath(shards))}-{reg}-s{seed}")
    cfg = make_config(shards, out, preset=preset, reg=reg, gamma=gamma, gamma_ramp=gamma_ramp, gamma_start=gamma_start,
                      epochs=epochs, batch_size=batch_size, lr=lr, weight_decay=weight_decay, width=width, seed=seed,
                      workers=workers, threads=threads, device=device, format=fmt, cache=cache,
                      checkpoint_every=checkpoint_every, rank_check=rank_check, val=val)
    if rank0:
        click.echo(f"data: {shards}; preset: {preset} ({why}); regularizer: {describe_regularizer(cfg, shards)}; "
                   f"run folder: {out}", err=True)
    path = run_fit(cfg, resume=resume, progress=not quiet, overwrite=overwrite, allow_incomplete=allow_incomplete,
                   echo=lambda line: click.echo(line, err=True))
    if rank0:
        summary = last_epoch_summary(os.path.dirname(path))
        if summary:
            click.echo(summary, err=True)
        click.echo(f"model: {path}")


def last_epoch_summary(run: str) -> str | None:
    """One closing line from the run's history.json: the last epoch's training error (and regularizer) and, with
    --val, the validation error — the normalized L1 of docs/training.md §Losses — and where the physical units are.
    None when the history cannot be read (the model is written all the same)."""
    try:
        with open(os.path.join(run, "history.json")) as f:
            last = json.load(f)[-1]
        parts = [f"epoch {last['epoch'] + 1}: training error {last['train_error']:.4g}"]
    except (OSError, ValueError, LookupError, TypeError):
        return None
    if last.get("train_reg"):
        parts.append(f"regularizer {last['train_reg']:.4g}")
    if last.get("val_error") is not None:
        parts.append(f"validation error {last['val_error']:.4g}")
    return ("; ".join(parts) + " (L1 on normalized targets; `risp-train eval MODEL SHARDS` gives metres and "
            "degrees against the baselines)")


def describe_regularizer(cfg, shards: str) -> str:
    """``stochastic, γ 0.3 from 50% of the steps, ramped in over 50% of the rest``: the schedule as resolved for the
    data's environment (per-environment defaults, docs/training.md §γ schedule)."""
    from .config import resolved_gamma, resolved_gamma_start

    env = dataset_env(shards)
    if cfg.reg == "none" or env is None:
        return cfg.reg
    gamma, start = resolved_gamma(cfg, env), resolved_gamma_start(cfg, env)
    return (f"{cfg.reg}, γ {gamma:g}" + (f" from {start:.0%} of the steps," if start else "")
            + f" ramped in over {cfg.gamma_ramp:.0%} of the {'rest' if start else 'steps'}")


def dataset_env(folder: str) -> str | None:
    """The environment a shard folder holds (None when its manifest cannot be read: fit then says why)."""
    from risp_data.shards import load_manifest

    try:
        return load_manifest(folder)["env"]
    except RispError:
        return None


def find_dataset(folder: str, need_jacobian: bool) -> str:
    """The shard folder to train on: ``folder`` itself when it holds a manifest.json, else its one data-set
    subfolder, or, among several, its one train-domain set (with Jacobians when ``need_jacobian``)."""
    import json

    if os.path.isfile(folder):
        raise RispError(f"{folder} is a file, not a shard folder; give the folder risp-data render wrote")
    if not os.path.isdir(folder):
        raise RispError(f"shard folder {folder} does not exist; render one with `risp-data render --env ENV --n N`")
    if os.path.exists(os.path.join(folder, "manifest.json")):
        return folder
    sets, unreadable = {}, []
    for name in sorted(os.listdir(folder)):
        path = os.path.join(folder, name, "manifest.json")
        if os.path.isfile(path):
            try:
                with open(path) as f:
                    manifest = json.load(f)
            except (OSError, ValueError) as e:
                unreadable.append(f"{path} ({type(e).__name__})")
                continue
            if isinstance(manifest, dict):  # valid JSON that is not an object is another tool's file: passed over
                sets[os.path.join(folder, name)] = manifest
    if unreadable:  # a damaged data set (risp writes manifests atomically) is not silently passed over for another
        raise RispError(f"{folder}: unreadable manifest {unreadable[0]}; repair it (`risp-data render` with the same "
                        "options resumes a folder) or move that folder away")
    if len(sets) == 1:
        return next(iter(sets))
    usable = [p for p, m in sets.items() if m.get("domain") == "train" and (m.get("jacobian") or not need_jacobian)]
    if len(usable) == 1:
        return usable[0]
    if not sets:
        raise RispError(f"{folder} holds no data set (no manifest.json in it or its subfolders); "
                        "render one with `risp-data render --env ENV --n N`")
    listing = ", ".join(f"{p} ({m.get('env')}, {m.get('domain')}, n={m.get('n')})" for p, m in sets.items())
    raise RispError(f"{folder} holds {len(sets)} data sets: {listing}; pass one of them")


@cli.command("eval")
@click.argument("model", type=click.Path())
@click.argument("shards", type=click.Path())
@click.option("--metric", default="l1", show_default=True, help="Per-image state error: l1 (mean |Δs|) or l2 (‖Δs‖).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the random baseline.")
@click.option("--batch-size", type=int, default=32, show_default=True)
@click.option("--limit", type=int, default=None, help="Evaluate at most this many images.")
@click.option("--format", "fmt", default="auto", show_default=True, help="wds or zarr (auto: wds if present).")
@click.option("--out", default=None, help="Path prefix of the .json and .md results [MODEL_DIR/eval-SHARDS_NAME].")
@click.option("--threads", type=int, default=0, show_default=True, help="torch threads (0: one per available CPU).")
@click.option("--overwrite", is_flag=True, help="Replace the results an earlier evaluation wrote under the --out prefix.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def eval_cmd(model, shards, metric, seed, batch_size, limit, fmt, out, threads, overwrite, quiet):
    """State-estimation error of MODEL (a checkpoint, or a run folder's model.pt) on SHARDS, with the average and
    random baselines."""
    from risp_data.threads import set_torch_threads

    from .checkpoint import model_file
    from .evaluate import EvalConfig, evaluate, markdown_table

    set_torch_threads(threads)

    res = evaluate(EvalConfig(model=model_file(model), shards=shards, metric=metric, seed=seed, batch_size=batch_size,
                              limit=limit, format=fmt, out=out, overwrite=overwrite), progress=not quiet)
    click.echo(markdown_table(res))
    click.echo(f"written: {', '.join(res['files'])}")
    if res.get("manifest_hash") and res["manifest_hash"] == res.get("train_manifest_hash"):
        click.echo(f"note: {shards} is the data the model was trained on: these figures are training error, not what "
                   "it does on images it never saw (evaluate on a --domain target folder for that)", err=True)
    from .data import open_shards, sample_counts

    counts = sample_counts(open_shards(shards, fmt))
    if counts["used"] < counts["rendered_n"]:  # fit refuses such a folder; an evaluation on it may be meant, say so
        click.echo(f"note: {shards} is incomplete ({counts['used']} of {counts['rendered_n']} samples rendered): "
                   "the figures are over those; rerun its risp-data render command to finish it", err=True)


@cli.command()
@click.option("--env", type=click.Choice(ENV_NAMES), required=True, help="Environment.")
@click.option("--out", required=True, type=click.Path(file_okay=False), help="Ablation folder (shards, runs, results).")
@click.option("--pools", default="1,10,per-sample", show_default=True, help="Rendering-configuration pool sizes (comma-separated; per-sample = a new one per sample).")
@click.option("--regs", default="none,surrogate,exact,stochastic", show_default=True, help="Regularizers to compare (comma-separated).")
@click.option("--n-train", type=int, default=512, show_default=True, help="Training samples per pool.")
@click.option("--n-eval", type=int, default=128, show_default=True, help="Samples per evaluation set.")
@click.option("--res", "resolution", type=int, default=64, show_default=True, help="Image resolution.")
@click.option("--spp", type=int, default=8, show_default=True, help="Samples per pixel.")
@click.option("--shard-size", type=int, default=64, show_default=True)
@click.option("--preset", type=click.Choice(PRESET_CHOICES), default="cpu", show_default=True, help="Training preset.")
@click.option("--epochs", type=int, default=None, help="Epochs [preset].")
@click.option("--batch-size", type=int, default=None, help="Batch size [preset].")
@click.option("--width", type=int, default=None, help="ResNet-18 width [preset].")
@click.option("--lr", type=float, default=None, help="Learning rate [preset].")
@click.option("--gamma", type=float, default=None, help="Final γ [risp-train's per-environment default: GAMMA_DEFAULTS, docs/training.md].")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--workers", type=int, default=2, show_default=True, help="DataLoader workers per training.")
@click.option("--no-target", is_flag=True, help="Skip the target-domain evaluation set.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def ablation(env, out, pools, regs, n_train, n_eval, resolution, spp, shard_size, preset, epochs, batch_size, width,
             lr, gamma, seed, workers, no_target, quiet):
    """Data-efficiency ablation (1 / 10 / per-sample rendering configurations × regularizers)."""
    from .ablation import AblationConfig, ablation_markdown, run_ablation

    cfg = AblationConfig(env=env, out=out, pools=tuple(p.strip() for p in pools.split(",") if p.strip()),
                         regs=tuple(r.strip() for r in regs.split(",") if r.strip()), n_train=n_train,
                         n_eval=n_eval, resolution=resolution, spp=spp, shard_size=shard_size, seed=seed,
                         preset=preset, epochs=epochs, batch_size=batch_size, width=width, lr=lr, gamma=gamma,
                         workers=workers, target=not no_target)
    summary = run_ablation(cfg, progress=not quiet)
    click.echo(ablation_markdown(summary))
    click.echo(f"written: {out}/ablation.json, ablation.md, ablation.png")


def main() -> None:
    run_cli(cli)


if __name__ == "__main__":
    main()
