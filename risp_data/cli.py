"""``risp-data``: render shards, inspect them, verify their Jacobians (docs/cli-data.md).

Thin layer: click options -> a frozen config -> a pure function in generate / inspect / verify.
"""

from __future__ import annotations

import os
import time

import click

from .cli_util import RispGroup, run_cli
from .envs import ENV_NAMES
from .threads import available_cpus

# the option choices (click lists them in --help and refuses others in one line); literals here because the modules
# that own them import Mitsuba or numpy, which --help should not wait for — tests/test_data_cli.py checks they agree
FORMAT_CHOICES = ("wds", "zarr", "both")
DOMAINS = ("train", "target")  # risp_data.psi.DOMAINS (psi imports numpy)
EXECUTORS = ("local", "ray")  # risp_data.generate.EXECUTORS
JACOBIAN_PATHS = ("fast", "legacy")  # risp_data.render.JACOBIAN_PATHS


@click.group(cls=RispGroup)
@click.version_option(package_name="risp", message="%(prog)s (risp) %(version)s")
def cli():
    """Randomized Mitsuba renders with forward-mode Jacobian stacks, as webdataset and zarr shards."""


@cli.command()
@click.option("--env", "env", type=click.Choice(ENV_NAMES), required=True, help="Environment.")
@click.option("--n", "n", required=True, type=int, help="Number of samples (> 0).")
@click.option("--out", "out", default=None, help="Output folder (created; resumed if it holds this job) [shards/ENV-DOMAIN].")
@click.option("--format", "fmt", type=click.Choice(FORMAT_CHOICES), default="both", show_default=True,
              help="Shard format(s) to write.")
@click.option("--res", "resolution", default=64, show_default=True, type=int, help="Image width = height in pixels.")
@click.option("--spp", default=16, show_default=True, type=int, help="Samples per pixel.")
@click.option("--domain", type=click.Choice(DOMAINS), default="train", show_default=True,
              help="Look distribution (docs/rendering.md).")
@click.option("--seed", default=0, show_default=True, type=int, help="Run seed (>= 0); sample i uses SeedSequence(seed, spawn_key=(i,)).")
@click.option("--workers", default=None, type=int, help="Parallel workers (default: the CPUs this process may use, its affinity mask).")
@click.option("--shard-size", default=256, show_default=True, type=int, help="Samples per shard (= per task).")
@click.option("--executor", type=click.Choice(EXECUTORS), default="local", show_default=True,
              help="local (process pool) or ray (needs risp[ray]).")
@click.option("--no-jacobian", is_flag=True, help="Store images only (evaluation shards).")
@click.option("--variant", default=None, help="Mitsuba variant: llvm_ad_rgb or cuda_ad_rgb (default: cuda if usable).")
@click.option("--jacobian-path", type=click.Choice(JACOBIAN_PATHS), default="fast", show_default=True,
              help="fast (merged colour tangents, emitter-split primal) or legacy (one tangent pass per psi; "
                   "kept for one release). Same J to float32 rounding (docs/rendering.md).")
@click.option("--full-jacobian", is_flag=True,
              help="Store all three channels of every dI/dpsi_j (default: a material colour's own channel only, "
                   "where the other two are exactly zero; docs/formats.md).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def render(env, n, out, fmt, resolution, spp, domain, seed, workers, shard_size, executor, no_jacobian, variant,
           jacobian_path, full_jacobian, quiet):
    """Render N samples of ENV into shards under OUT (resumable: rerun to complete missing shards)."""
    from .errors import RispError
    from .generate import RenderJob, run_job, validate_job

    default_out = out is None
    if default_out:  # the user's command `risp-data render --env cube --n 10000` works as written
        out = os.path.join("shards", f"{env}-{domain}")

    if no_jacobian and full_jacobian:  # one asks for no Jacobians, the other for all their channels
        raise RispError("--full-jacobian sets how Jacobians are stored; --no-jacobian renders none (give one of them)")
    formats = {"both": ("wds", "zarr"), "wds": ("wds",), "zarr": ("zarr",)}[fmt]  # click.Choice checked fmt
    job = RenderJob(
        env=env,
        n=n,
        out=out,
        domain=domain,
        formats=formats,
        resolution=resolution,
        spp=spp,
        seed=seed,
        workers=workers if workers is not None else available_cpus(),  # the CPUs this process may use (taskset)
        shard_size=shard_size,
        executor=executor,
        jacobian=not no_jacobian,
        variant=variant,
        jacobian_path=jacobian_path,
        compact_jacobian=not full_jacobian,
    )
    validate_job(job)  # a bad name is the one line printed, before the default folder is announced
    if default_out:
        click.echo(f"output folder: {out}", err=True)
    t0 = time.perf_counter()
    stats: dict = {}
    manifest = run_job(job, progress=not quiet, log=lambda s: click.echo(s, err=True), stats=stats)
    dt = time.perf_counter() - t0
    done = stats.get("rendered_samples", 0)  # rendered by this call (not shards merged or found on disk)
    rate = done / dt if dt > 0 else float("nan")
    click.echo(
        f"{out}: {manifest['counts']['complete_samples']}/{manifest['n']} samples in "
        f"{manifest['counts']['complete_shards']}/{manifest['num_shards']} shards; "
        f"rendered {done} now in {dt:.1f} s ({rate:.2f} samples/s)"
    )


@cli.command()
@click.argument("folder", type=click.Path())
@click.option("--png", default=None, type=click.Path(dir_okay=False), help="Contact sheet path (default: FOLDER/contact_sheet.png).")
@click.option("--samples", default=4, show_default=True, type=int, help="Rows (samples) in the contact sheet.")
@click.option("--deep", is_flag=True, help="Also hash every shard file (sha256 against the manifest).")
def inspect(folder, png, samples, deep):
    """Print the manifest summary of FOLDER, check every listed shard (sizes, sample counts; sha256 with
    --deep; exit 1 when one is damaged) and write a PNG contact sheet of images and Jacobians."""
    from .errors import RispError
    from .inspect import InspectConfig, inspect_folder
    from .shards.manifest import repair_hint

    if png is not None and not png.lower().endswith(".png"):  # the sheet is written as PNG whatever the name
        raise RispError(f"--png {png}: the contact sheet is a PNG image; give a path ending in .png")
    summary, path, problems = inspect_folder(InspectConfig(folder=folder, png=png, samples=samples, deep=deep))
    click.echo(summary)
    if problems:
        raise RispError(f"{len(problems)} damaged shard(s) in {folder}{repair_hint(folder)}")
    click.echo(f"contact sheet: {path}" if path else "contact sheet: none (no complete shard yet)")


@cli.command()
@click.argument("folder", type=click.Path())
@click.option("--samples", default=8, show_default=True, type=int, help="Samples to re-render (evenly spaced).")
@click.option("--eps", default=1e-2, show_default=True, type=float,
              help="Step, as a fraction of each psi's range in the folder's domain (manifest psi.low/high).")
@click.option("--tol", default=1e-3, show_default=True, type=float,
              help="Largest accepted relative error per psi (measured <= 2.5e-5 at --eps 1e-2; docs/cli-data.md).")
@click.option("--checksums/--no-checksums", default=True, show_default=True, help="Also hash every shard file.")
@click.option("--repair", is_flag=True, help="First re-render missing or damaged shards (the manifest's job).")
def verify(folder, samples, eps, tol, checksums, repair):
    """Compare stored Jacobians with central differences of re-renders (same seed); exit 1 beyond --tol."""
    from .verify import VerifyConfig, format_report, verify_folder

    report = verify_folder(VerifyConfig(folder=folder, samples=samples, eps=eps, tol=tol, checksums=checksums,
                                        repair=repair))
    click.echo(format_report(report))
    report.raise_if_failed()


def main() -> None:
    run_cli(cli)


if __name__ == "__main__":
    main()
