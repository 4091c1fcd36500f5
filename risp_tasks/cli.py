"""``risp-task``: tasks on measured or estimated trajectories (``risp task …`` is the same group).

    risp-task diagnose DATA… --env E --out report/ [--seed 0]

Thin layer: click options -> :class:`risp_tasks.diagnose.run.DiagnoseConfig` -> ``diagnose``.
Documentation: docs/cli-task.md.
"""

from __future__ import annotations

import click

from risp_data.cli_util import RispGroup, run_cli
from risp_data.envs import ENV_NAMES


@click.group(cls=RispGroup)
def cli():
    """Tasks on measured trajectories: diagnose what the simulator misses (more to come: estimate, sysid)."""


@cli.command()
@click.argument("data", nargs=-1, required=True, type=click.Path())
@click.option("--env", type=click.Choice(ENV_NAMES), required=True, help="environment of the data")
@click.option("--out", type=click.Path(file_okay=False), required=True, help="output folder (report.md, report.json, plots)")
@click.option("--seed", type=int, default=0, show_default=True, help="seed of the fitting/held-out split and the bootstrap")
@click.option("--held-out", type=float, default=0.3, show_default=True,
              help="fraction held out: of the trajectories (several files) or of the time span (one file)")
@click.option("--horizon", type=int, default=10, show_default=True, help="multiple-shooting segment length [samples]")
@click.option("--rollout-horizon", type=int, default=None, help="open-loop horizon of the reported rollout error [samples] (default 3×horizon)")
@click.option("--max-segments", type=int, default=600, show_default=True, help="cap on segments per split (seeded subset)")
@click.option("--max-iters", type=int, default=25, show_default=True, help="Levenberg–Marquardt iterations per model")
@click.option("--pairs-top", type=int, default=3, show_default=True, help="pairs are formed among this many best single effects")
@click.option("--effects", default=None, help="comma-separated subset of the effect library to try (default: all)")
@click.option("--limit", type=int, default=None, help="use only the first N files (sorted by name)")
@click.option("--floor-offset", default="auto", show_default=True,
              help="cube: floor height in the data's frame [m], or 'auto' (median lowest corner of resting frames)")
@click.option("--side", type=float, default=None, help="cube side [m] (overrides the sidecar)")
@click.option("--mass", type=float, default=None, help="cube mass [kg] (overrides the sidecar)")
@click.option("--no-plots", is_flag=True, help="skip the PNG plots")
@click.option("--quiet", is_flag=True, help="no progress bar")
def diagnose(data, env, out, seed, held_out, horizon, rollout_horizon, max_segments, max_iters, pairs_top, effects,
             limit, floor_offset, side, mass, no_plots, quiet):
    """Show what the simulator gets wrong in measured DATA (CSV files or folders), name the cause, measure the gain."""
    from risp_tasks.diagnose.run import DiagnoseConfig
    from risp_tasks.diagnose.run import diagnose as run_diagnose

    from risp_data.errors import RispError

    if floor_offset != "auto":
        try:
            floor_offset = float(floor_offset)
        except ValueError:
            raise RispError(f"--floor-offset must be 'auto' or a number of metres, got {floor_offset!r}") from None
    cfg = DiagnoseConfig(
        data=tuple(data), env=env, out=out, seed=seed, held_out=held_out, horizon=horizon,
        rollout_horizon=rollout_horizon, max_segments=max_segments, max_iters=max_iters, pairs_top=pairs_top,
        effects=None if effects is None else tuple(e.strip() for e in effects.split(",") if e.strip()),
        limit=limit, floor_offset=floor_offset, side=side, mass=mass, plots=not no_plots, progress=not quiet,
    )
    report = run_diagnose(cfg)
    click.echo(f"cause: {report['cause']} — {report['reason']}")
    for name, p in report["parameters"].items():
        click.echo(f"  {name} = {p['value']:.4g} ± {p['std']:.2g} {p['unit']}")
    click.echo(f"held-out normalised RSS gain: {report['gain']['normalized_rss']:+.1%}; report: {out}/report.md")


def main():
    run_cli(cli)


if __name__ == "__main__":
    main()
