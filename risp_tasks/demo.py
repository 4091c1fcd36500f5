"""``risp demo``: the main job on a small built-in default — render → train → task — in one folder.

One job, one seed, one self-describing output folder (``demo/`` by default):

    preview/<env>-<domain>/  a few samples of every environment in both domains, with contact sheets
    shards/cube-train/       a small cube training set with Jacobian stacks
    shards/cube-heldout/     held-out training-domain shards (unseen ψ) for evaluation
    shards/cube-target/      target-domain shards (another look: lights, materials, floor, integrator)
    runs/cube/               a RISP network trained with the stochastic regularizer, loss curve, evaluations
    diagnose/                ``risp-task diagnose`` on real cube tosses: report.md, report.json, plots
    demo.json                the seed, the sizes and every command that was run
    README.md                what is where, with the headline numbers

Every step is the public command-line tool, called in-process, so the demo doubles as a usage example.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import click

from risp_data.envs import ENV_NAMES
from risp_data.errors import RispError

BUNDLED_TOSSES = Path(__file__).parent / "data" / "cube_tosses"


@dataclass(frozen=True)
class DemoConfig:
    out: str
    seed: int
    preview_n: int = 4  # samples per environment and domain in the preview shards
    preview_res: int = 48
    train_n: int = 192  # cube training samples (with Jacobians)
    heldout_n: int = 48
    res: int = 32  # training resolution
    spp: int = 8
    epochs: int = 6
    reg: str = "stochastic"
    n_tosses: int = 12  # real cube tosses given to diagnose


QUICK = dict(preview_n=2, preview_res=16, train_n=32, heldout_n=16, res=16, spp=2, epochs=1, n_tosses=4)


def _run(group: click.Group, args: list[str], log: list[dict]) -> None:
    """Run one public CLI command in-process; a failure stops the demo with that command's message."""
    name = group.name or "risp"
    click.secho(f"\n$ {name} {' '.join(args)}", fg="cyan")
    t0 = time.perf_counter()
    try:
        group.main(args=args, prog_name=name, standalone_mode=False)
    except click.ClickException as e:
        raise RispError(f"`{name} {args[0]}` failed: {e.format_message()}") from None
    log.append({"command": f"{name} {' '.join(args)}", "seconds": round(time.perf_counter() - t0, 2)})


def run_demo(cfg: DemoConfig) -> Path:
    """Render previews of all environments, train on cube, evaluate, diagnose real tosses. Returns the folder."""
    from risp_data.cli import cli as data_cli
    from risp_train.cli import cli as train_cli
    from risp_tasks.cli import cli as task_cli

    data_cli.name, train_cli.name, task_cli.name = "risp-data", "risp-train", "risp-task"
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    log: list[dict] = []
    seed = str(cfg.seed)

    # 1. Render: every environment in both domains, and its contact sheet.
    for env in ENV_NAMES:
        for domain in ("train", "target"):
            folder = out / "preview" / f"{env}-{domain}"
            _run(data_cli, ["render", "--env", env, "--domain", domain, "--n", str(cfg.preview_n),
                            "--res", str(cfg.preview_res), "--spp", str(cfg.spp), "--seed", seed,
                            "--format", "wds", "--shard-size", str(cfg.preview_n), "--out", str(folder)], log)
            _run(data_cli, ["inspect", str(folder), "--samples", str(min(cfg.preview_n, 3))], log)

    # 2. A small cube training set (with Jacobians), held-out and target-domain evaluation sets.
    shards = out / "shards"
    common = ["--env", "cube", "--res", str(cfg.res), "--spp", str(cfg.spp), "--format", "wds"]
    _run(data_cli, ["render", *common, "--n", str(cfg.train_n), "--seed", seed,
                    "--shard-size", str(max(8, cfg.train_n // 4)), "--out", str(shards / "cube-train")], log)
    _run(data_cli, ["render", *common, "--n", str(cfg.heldout_n), "--seed", str(cfg.seed + 1), "--no-jacobian",
                    "--shard-size", str(cfg.heldout_n), "--out", str(shards / "cube-heldout")], log)
    _run(data_cli, ["render", *common, "--n", str(cfg.heldout_n), "--seed", str(cfg.seed + 2), "--no-jacobian",
                    "--domain", "target", "--shard-size", str(cfg.heldout_n), "--out", str(shards / "cube-target")],
         log)

    # 3. Train RISP (CPU preset, stochastic regularizer) and evaluate against the baselines.
    run = out / "runs" / "cube"
    _run(train_cli, ["fit", str(shards / "cube-train"), "--out", str(run), "--reg", cfg.reg, "--preset", "cpu",
                     "--epochs", str(cfg.epochs), "--seed", seed, "--workers", "1",
                     "--val", str(shards / "cube-heldout"), *(["--resume"] if (run / "last.pt").exists() else [])], log)
    for name in ("cube-heldout", "cube-target"):
        _run(train_cli, ["eval", str(run / "model.pt"), str(shards / name), "--seed", seed,
                         "--out", str(run / f"eval-{name}")], log)

    # 4. A task: diagnose what the base cube model misses in real, motion-captured tosses.
    tosses = sorted(BUNDLED_TOSSES.glob("toss_*.csv"))[: cfg.n_tosses]
    if not tosses:
        raise RispError(f"bundled cube tosses missing from {BUNDLED_TOSSES}")
    _run(task_cli, ["diagnose", *map(str, tosses), "--env", "cube", "--seed", seed,
                    "--out", str(out / "diagnose")], log)

    _write_summary(out, cfg, log)
    return out


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _write_summary(out: Path, cfg: DemoConfig, log: list[dict]) -> None:
    (out / "demo.json").write_text(json.dumps({"config": asdict(cfg), "seed": cfg.seed, "commands": log}, indent=2))
    lines = [
        "# risp demo",
        "",
        f"Seed {cfg.seed}. Every command that was run, with its wall time, is in `demo.json`.",
        "",
        "## What is where",
        "- `preview/<env>-<domain>/contact_sheet.png`: rendered images and their Jacobian images ∂I/∂ψ_j",
        "- `shards/cube-train/`: the training shards (webdataset tar + manifest.json)",
        "- `runs/cube/`: checkpoint, `losses.csv`, loss-curve PNG `losses.png`, evaluations (`eval-*.md`)",
        "- `diagnose/`: `report.md`, `report.json` and plots of the real cube-toss diagnosis",
        "",
    ]
    evals = {name: _read_json(out / "runs" / "cube" / f"eval-{name}.json") for name in ("cube-heldout", "cube-target")}
    if any(evals.values()):
        lines += ["## State estimation (cube)", "",
                  "Mean per-image L1 error over the whole state and over the position (x, y, z) alone. A uniformly",
                  "coloured cube looks the same under 24 rotations, so its yaw/pitch/roll cannot be read from an",
                  "image and dominate the whole-state error; the position columns show what the network learned.",
                  "", "| shards | method | whole state | position (m) |", "|---|---|---:|---:|"]
        for name, ev in evals.items():
            for method, res in (ev or {}).get("results", {}).items():
                names = ev.get("state_names", [])
                pos = [res["per_dim_mae"][names.index(c)] for c in ("x", "y", "z") if c in names]
                pos_txt = f"{sum(pos) / len(pos):.3f}" if pos else "–"
                lines.append(f"| {name} | {method} | {res['mean']:.3f} | {pos_txt} |")
        lines.append("")
    rep = _read_json(out / "diagnose" / "report.json")
    if rep:
        lines += ["## Diagnose (real cube tosses)", "", f"- verdict: **{rep.get('cause')}** "
                  f"(best model: `{rep.get('compared_model') or rep.get('selected_model')}`; see diagnose/report.md)"]
        for pname, p in (rep.get("parameters") or {}).items():
            unit = "" if p.get("unit") in (None, "", "1") else f" {p['unit']}"
            lines.append(f"- {pname} = {p['value']:.4g} ± {p['std']:.2g}{unit}")
        rollout = (rep.get("gain") or {}).get("rollout", {})
        if rollout:
            lines.append("- held-out open-loop rollout error reduction: "
                         + ", ".join(f"{k} {100 * v:+.0f} %" for k, v in rollout.items()))
        lines.append("")
    (out / "README.md").write_text("\n".join(lines))


@click.command("demo")
@click.option("--out", default="demo", show_default=True, type=click.Path(file_okay=False), help="Output folder.")
@click.option("--seed", default=0, show_default=True, type=int, help="Seed of every step (recorded in demo.json).")
@click.option("--quick", is_flag=True, help="An even smaller run (seconds, used by the tests).")
def demo(out: str, seed: int, quick: bool) -> None:
    """Render → train → task on a small built-in default (minutes on a 2-core CPU)."""
    cfg = DemoConfig(out=out, seed=seed, **(QUICK if quick else {}))
    t0 = time.perf_counter()
    try:
        folder = run_demo(cfg)
    except RispError as e:
        raise click.ClickException(str(e)) from None
    click.secho(f"\ndemo finished in {time.perf_counter() - t0:.0f} s: see {folder / 'README.md'}", fg="green")
