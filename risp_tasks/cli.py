"""``risp-task``: tasks on measured or estimated trajectories (``risp task …`` is the same group).

    risp-task diagnose DATA… --env E --out report/ [--seed 0]
    risp-task estimate|sysid|imitate VIDEO [--model M] [--loss render|state|oracle|pixelwise|perceptual] …
    risp-task control TARGET.png [--model M] [--initial-state S.json] [--horizon 10]
    risp-task make-video --env E --out video.mp4 [--frames 20] [--fps 10] [--resolution 64] [--seed 0]
    risp-task table --table estimation|sysid|imitation|control|regularizers|sampling [--preset cpu|paper] …

Thin layer: click options -> a config (``DiagnoseConfig``, ``TaskConfig``, the table's) -> the package's function.
Documentation: docs/cli-task.md.
"""

from __future__ import annotations

import contextlib
import os
import re

import click

from risp_data.cli_util import RispGroup, run_cli
from risp_data.envs import ENV_NAMES


@click.group(cls=RispGroup)
@click.version_option(package_name="risp", message="%(prog)s (risp) %(version)s")
def cli():
    """From a video to states, physical parameters and actions (estimate, sysid, imitate, control); diagnose
    measured data; make reference videos (make-video); the paper's tables (table)."""


@cli.command()
@click.argument("data", nargs=-1, required=True, type=click.Path())
@click.option("--env", type=click.Choice(ENV_NAMES), required=True, help="environment of the data")
@click.option("--out", type=click.Path(file_okay=False), required=True, help="output folder (report.md, report.json, plots): new, empty or an earlier report, replaced whole")
@click.option("--seed", type=int, default=0, show_default=True, help="seed of the fitting/held-out split and the bootstrap")
@click.option("--held-out", type=float, default=0.3, show_default=True,
              help="fraction held out: of the trajectories (several files) or of the time span (one file)")
@click.option("--horizon", type=int, default=10, show_default=True, help="multiple-shooting segment length [samples]")
@click.option("--rollout-horizon", type=int, default=None, help="open-loop horizon of the reported rollout error [samples] (default 3×horizon)")
@click.option("--max-segments", type=int, default=600, show_default=True, help="cap on segments per split (seeded subset)")
@click.option("--max-iters", type=int, default=25, show_default=True, help="Levenberg–Marquardt iterations per model")
@click.option("--pairs-top", type=int, default=3, show_default=True, help="pairs are formed among this many best single effects")
@click.option("--effects", default=None, help="comma-separated subset of the effect library to try (default: all)")
@click.option("--limit", type=int, default=None, help="use only the first N files: in the order given, a folder's CSVs in name order")
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
    floor = report["data"].get("floor_calibration", {})
    if floor.get("mode") == "auto" and not floor.get("applied"):  # a few short tosses: the fitting part rests briefly
        click.echo(f"note: the floor was not calibrated: {floor.get('rest_frames', 0)} resting frames in the fitting "
                   f"part, 20 needed; give --floor-offset (docs/measured-data.md §Floor calibration)")
    for name, p in report["parameters"].items():
        unit = "" if p["unit"] in ("1", "", None) else f" {p['unit']}"  # "1": dimensionless
        click.echo(f"  {name} = {p['value']:.4g} ± {p['std']:.2g}{unit}")
    click.echo(f"held-out normalised RSS gain: {report['gain']['normalized_rss']:+.1%}; report: {os.path.join(os.path.normpath(out), 'report.md')}")


class _Knots(click.ParamType):
    """--action-knots: a whole number, or ``auto`` (imitate's cross-validated choice)."""

    name = "K|auto"

    def convert(self, value, param, ctx):
        try:
            return int(value)
        except (TypeError, ValueError):  # "auto", or a word TaskConfig refuses in its one error line
            return value


KNOTS = _Knots()


# The options of _task_options that only some tasks use, and those tasks.  The others still accept them (hidden
# from their --help), so that TaskConfig can say in one line why the option is not theirs.
ONLY_FOR = {"--grow-horizon": ("sysid", "imitate"), "--action-knots": ("imitate", "control"),
            "--params": ("imitate", "control"), "--actions": ("sysid", "estimate"),
            "--every": ("estimate", "sysid", "imitate"), "--source-fps": ("estimate", "sysid", "imitate"),
            "--fit-initial-state": ("sysid", "imitate"), "--fit-params": ("imitate",),
            "--initial-state": ("control",), "--horizon": ("control",)}


#: "sysid, imitate: " at the start of a shared option's help: whose option it is, dropped in those tasks' own help
TASKS_PREFIX = re.compile(r"^((?:estimate|sysid|imitate|control)(?:, (?:estimate|sysid|imitate|control))*): ")


def _task_options(task: str):
    """Options shared by the tasks (docs/cli-task.md); defaults are the paper's (RMSProp, lr 3e-3, momentum 0.5).
    ``task``'s --help lists those it uses (:data:`ONLY_FOR`)."""
    def shown(name: str) -> dict:
        return {"hidden": task not in ONLY_FOR.get(name, (task,))}

    opts = [
        click.option("--model", default=None, help="risp-train checkpoint or run folder (default: the most recent "
                     "runs/*/model.pt of the system --env " + ("names" if task == "control" else "or the video's "
                     "make-video tag names") + ", else the most recent)"),
        click.option("--runs", default="runs", show_default=True, help="where to look for the most recent model"),
        click.option("--env", type=click.Choice(ENV_NAMES), default=None, help="the system: picks the newest run of "
                     "it without --model, checks the model with it (default: the model's)"),
        click.option("--out", default=None, help="result folder (default results/<task>-<video>-seed<seed>)"),
        click.option("--overwrite", is_flag=True, help="replace an existing result folder at --out (a task's only)"),
        click.option("--loss", type=click.Choice(("render", "state", "oracle", "pixelwise", "perceptual")), default="state",
                     show_default=True, help="render: N(render(sim)) vs N(video); state: sim vs N(video); oracle: vs "
                     "--truth; pixelwise: render(sim) vs video; perceptual: F(render(sim)) vs F(video)"),
        click.option("--residual", type=click.Choice(("l2", "l1")), default=None,
                     help="render/state/oracle losses: squared (l2, the paper's) or absolute (l1, robust to the "
                          "network's occasional large misreadings) differences "
                          f"[default: {'l1' if task == 'sysid' else 'l2'}] (docs/tasks.md §Residual norm)"),
        click.option("--perceptual-weights", default=None, help="local torchvision vgg16 state dict for --loss "
                     "perceptual (default: the built-in filter bank)"),
        click.option("--init", type=click.Choice(("default", "random", "track", "scan")), default="default",
                     show_default=True,
                     help="initial guess" + (" (track, quadrotor only: a tracking controller along the estimated path; "
                                             "scan is sysid's)" if task == "imitate" else
                                             " (scan: the best of 17 points per parameter of the state loss over "
                                             "its range, then the descent from there; track is imitate's)"
                                             if task == "sysid" else "; track is imitate's, scan sysid's")),
        click.option("--optimizer", type=click.Choice(("rmsprop", "adam", "sgd")), default="rmsprop", show_default=True),
        click.option("--lr", type=float, default=3e-3, show_default=True),
        click.option("--momentum", type=float, default=0.5, show_default=True),
        click.option("--iterations", type=int, default=None, help="optimisation iterations " + (
            "[default: 0: the network's readings as they are]" if task == "estimate" else "[default: 100]")),
        click.option("--warm-start", type=int, default=0, show_default=True,
                     help="--loss render: run this many state-loss iterations first (docs/tasks.md §Warm start)"),
        click.option("--grow-horizon", type=int, default=0, show_default=True, **shown("--grow-horizon"),
                     help="sysid, imitate: over this many iterations the loss compares the first 2, 3, … frames, "
                          "then all (docs/tasks.md §Horizon curriculum)"),
        click.option("--action-knots", type=KNOTS, default=None, **shown("--action-knots"),
                     help="imitate, control: K >= 2 knots of a piecewise-linear command per action instead of one "
                          "row per frame (0); imitate: auto chooses K by cross-validation over the video's frames "
                          "[default: auto for imitate on the hand with --loss state or render and not --init track, else 0] "
                          "(docs/tasks.md §Smooth commands)"),
        click.option("--params", default=None, **shown("--params"),
                     help="imitate, control: known physical parameters — a JSON object, a JSON file, or a task's "
                          "result.json or result folder with identified parameters (e.g. sysid's) (default: the "
                          "simulator's nominal ones)"),
        click.option("--fit-initial-state/--fixed-initial-state", default=None, **shown("--fit-initial-state"),
                     help="sysid, imitate: identify the initial state read from the first two frames jointly, or keep "
                          "it fixed [default: fit; the rod starts at rest] (docs/tasks.md §Initial state)"),
        click.option("--fit-params/--no-fit-params", default=None, **shown("--fit-params"),
                     help="imitate: identify the physical parameters sysid would (quadrotor mass, hand stiffnesses, "
                          "rod log10 E) jointly with the actions, from the middle of their ranges or --params "
                          "[default: yes for the hand and the rod unless --params is given, no for the quadrotor] "
                          "(docs/tasks.md §Unknown physical parameters)"),
        click.option("--initial-state", default=None, **shown("--initial-state"),
                     help="control: JSON {'state': [...]} or {'env_state': [...]} (default: the simulator's)"),
        click.option("--horizon", type=int, default=None, **shown("--horizon"),
                     help="control: frames to reach the pictured state [default: 10]"),
        click.option("--seed", type=int, default=0, show_default=True),
        click.option("--every", type=int, default=1, show_default=True, **shown("--every"), help="keep every k-th frame"),
        click.option("--fps", type=float, default=None, help="resample the video to this frame rate (a divisor of the "
                     "video's own); control: the simulation's frame rate [default 10]"),
        click.option("--source-fps", type=float, default=None, **shown("--source-fps"), help="frame rate of a PNG folder; on a file, replaces its own rate"),
        click.option("--actions", default=None, **shown("--actions"), help="sysid, estimate: actions CSV (t + f0..f3 [N] / u0.. ; one row "
                     "per frame)"),
        click.option("--truth", default=None, help="ground-truth JSON (oracle loss, error report)"),
        click.option("--camera", default=None, help="camera JSON (intrinsics, extrinsics) replacing the environment's"),
        click.option("--mesh", default=None, help="quadrotor vehicle mesh (OBJ/PLY/STL/glTF, metres, body frame) to render"),
        click.option("--spp", type=int, default=4, show_default=True, help="samples per pixel of the differentiable renderer's gradient pass"),
        click.option("--primal-spp", type=int, default=None, help="samples per pixel of the rendered frames the network reads "
                     "(render loss) or the image losses compare [default: --spp] (docs/tasks.md §Primal spp)"),
        click.option("--looks", type=int, default=1, show_default=True,
                     help="--loss render: average the network's readings of each rendered frame over this many random "
                          "train-domain looks (1: the nominal look alone; K times the rendering; docs/tasks.md "
                          "§Several looks)"),
        click.option("--gradient", type=click.Choice(("flat", "mitsuba")), default="flat", show_default=True,
                     help="boundary term of the renderer's gradient: risp's for flat-shaded meshes, or Mitsuba's own "
                          "(cheaper, biased at creases and shadows; docs/tasks.md §Render-mode gradients)"),
        click.option("--threads", type=int, default=1, show_default=True, help="torch threads (0: one per available CPU)"),
        click.option("--render-threads", type=int, default=0, show_default=True,
                     help="Dr.Jit's CPU threads where the task renders (0: one per available CPU); recorded in "
                          "result.json timings.threads"),
        click.option("--no-plots", is_flag=True, help="skip the PNG plots"),
        click.option("--quiet", is_flag=True, help="no progress bar"),
    ]
    def decorate(f):
        for opt in reversed(opts):
            f = opt(f)
        for param in getattr(f, "__click_params__", []):  # "sysid, imitate: …" in sysid's own help says nothing
            said = TASKS_PREFIX.match(param.help or "")
            if said and task in said.group(1).split(", "):
                param.help = param.help[said.end():]
        return f
    return decorate


def _first_full(result: dict) -> int | None:
    """With --grow-horizon: the first iteration whose loss compares all frames (None if the horizon never got
    there); without it 0, the start."""
    full = result.get("frames_compared")
    if not full:
        return 0
    total = result.get("frames_in_loss", full[-1])
    return next((i for i, n in enumerate(full) if n == total), None)


def _loss_change(result: dict) -> str:
    """"loss A -> B": A the first loss over all compared frames (with --grow-horizon the first iterations compare
    fewer, and a two-frame loss is not comparable with the final one), B the returned iterate's."""
    loss, first = result["loss"], _first_full(result)
    if result.get("frames_compared"):
        if first is None or first >= len(loss):
            return f"loss {result['final_loss']:.4g} over all frames"
        return f"loss {loss[first]:.4g} (iteration {first}, the first over all frames) -> {result['final_loss']:.4g}"
    return f"loss {loss[0] if loss else result['final_loss']:.4g} -> {result['final_loss']:.4g}"


def out_of_memory_line(e: BaseException) -> str | None:
    """"out of GPU memory (tried to allocate 2.00 GiB)" for torch's out-of-memory errors — torch.OutOfMemoryError
    (CUDA), the CPU allocator's RuntimeError, Dr.Jit's "out of memory", MemoryError — else None."""
    import torch

    text = str(e)
    if not (isinstance(e, (MemoryError, torch.OutOfMemoryError)) or isinstance(e, RuntimeError) and (
            "can't allocate memory" in text or "out of memory" in text.lower())):
        return None
    where = "GPU memory" if isinstance(e, torch.OutOfMemoryError) or "CUDA" in text else "memory"
    cpu = re.search(r"allocate (\d+) bytes", text)  # DefaultCPUAllocator: "you tried to allocate N bytes"
    gpu = re.search(r"[Tt]ried to allocate ([\d.]+ [KMGT]?i?B)", text)  # CUDA: "Tried to allocate 2.00 GiB"
    size = f"{int(cpu.group(1)) / 2**30:.3g} GiB" if cpu else gpu.group(1) if gpu else None
    return f"out of {where}" + (f" (tried to allocate {size})" if size else "")


@contextlib.contextmanager
def _memory_hint(what: str, hint: str):
    """Torch's out-of-memory errors inside the block as one line saying what ran out and what to lower, not a
    traceback (the generic MemoryError line speaks of risp-data's --res and --workers)."""
    try:
        yield
    except Exception as e:
        line = out_of_memory_line(e)
        if line is None:
            raise
        from risp_data.errors import RispError

        raise RispError(f"{line} while {what}; {hint}") from None


def _run(task, video, **kw):
    from risp_tasks.tasks.config import TaskConfig
    from risp_tasks.tasks.run import run_task

    iterations = kw.pop("iterations")
    cfg = TaskConfig(task=task, video=video, iterations=(0 if task == "estimate" else 100) if iterations is None else iterations,
                     plots=not kw.pop("no_plots"), progress=not kw.pop("quiet"), **kw)
    fewer = "--horizon" if task == "control" else "--every or --fps, or a shorter video"
    with _memory_hint(f"running {task} on {video}", f"use fewer frames ({fewer}), a lower --spp/--primal-spp, "
                      "or --no-plots"):
        result = run_task(cfg, echo=click.echo)
    loss = result["loss"]
    if loss:
        click.echo(f"{task} ({result['env']}): {_loss_change(result)} in {len(loss)} iterations; results: {result['out']}")
    else:  # --iterations 0 (estimate's default): nothing was optimised, so no "loss A -> A in 0 iterations"
        what = (f"{result['video']['frames']} frames read by the network" if task == "estimate" else
                f"no optimisation (--iterations 0), loss {result['final_loss']:.4g} at the start")
        click.echo(f"{task} ({result['env']}): {what}; results: {result['out']}")
    first = _first_full(result)
    if loss and first is not None and first < len(loss) and result.get("best_iteration") == first:
        kept = ("the warm start's result is kept" if result["config"].get("warm_start") else
                "the start is kept — a smaller --lr or another --init may help")
        if first:  # a horizon curriculum: its first full-horizon iterate, not the start, is what no step beat
            kept = "that iterate is kept — a smaller --lr or a shorter --grow-horizon may help"
        start = "the start" if not first else f"iteration {first}, the first over all frames"
        click.echo(f"note: no step improved on {start} (loss {loss[first]:.4g}); {kept} (docs/tasks.md §Pipeline)")
    for name, value in result["estimates"].get("parameters", {}).items():
        click.echo(f"  {name} = {value:.4g}")
    fitted = set(result.get("info", {}).get("fitted_parameters", []))
    for name, value in result.get("info", {}).get("given_parameters", {}).items():
        if name not in fitted:  # a fitted one is printed above, where it ended
            click.echo(f"  {name} = {value:.4g} (from --params)")
    for name, value in result.get("errors", {}).items():
        if isinstance(value, float):
            click.echo(f"  {name} = {value:.4g}")
    for name, value in result.get("errors", {}).get("parameter_error_final", {}).items():
        click.echo(f"  {name} error = {value:.4g} (against --truth; {result['errors']['parameter_error_initial'][name]:.4g} "
                   f"at the start)")
    for warning in result.get("warnings", []):
        click.echo(f"warning: {warning}")
    return result


@cli.command()
@click.argument("video", type=click.Path())
@_task_options("estimate")
def estimate(video, **kw):
    """Per-frame states of VIDEO as a measured-data CSV (docs/measured-data.md) that `diagnose` reads."""
    _run("estimate", video, **kw)


@cli.command()
@click.argument("video", type=click.Path())
@_task_options("sysid")
def sysid(video, **kw):
    """The physical parameter(s) that reproduce VIDEO (quadrotor mass, cube log10 k_n, hand stiffness, rod log10 E)."""
    _run("sysid", video, **kw)


@cli.command()
@click.argument("video", type=click.Path())
@_task_options("imitate")
def imitate(video, **kw):
    """The action sequence that reproduces the motion in VIDEO (quadrotor, hand, rod)."""
    _run("imitate", video, **kw)


@cli.command()
@click.argument("target", type=click.Path())
@_task_options("control")
def control(target, **kw):
    """Actions that drive the system from its initial state to the state pictured in TARGET (a PNG or JPEG image)."""
    _run("control", target, **kw)


@cli.command("make-video")
@click.option("--env", type=click.Choice(ENV_NAMES), required=True)
@click.option("--out", required=True, help="video file (.mp4/.avi/.mov/.mkv) or folder of PNGs; ground truth beside it")
@click.option("--frames", type=int, default=20, show_default=True)
@click.option("--fps", type=float, default=10.0, show_default=True)
@click.option("--resolution", "--res", "resolution", type=int, default=64, show_default=True,
              help="frame side in pixels (--res as in risp-data)")
@click.option("--spp", type=int, default=16, show_default=True, help="samples per pixel (×4 in the target domain)")
@click.option("--domain", type=click.Choice(("target", "train")), default="target", show_default=True,
              help="target: the test look (random looks outside the training ranges, longer light paths, 4× --spp); "
                   "train: a look drawn as the networks' training images are")
@click.option("--params", default=None, help="JSON object of simulator parameters (default: random in the paper's ranges)")
@click.option("--effect", default=None, help="hidden effect NAME or NAME:v1,v2,… (e.g. wind:3,0,0)")
@click.option("--camera", default=None, help="camera JSON replacing the environment's camera")
@click.option("--mesh", default=None, help="quadrotor vehicle mesh (OBJ/PLY/STL/glTF, metres, body frame)")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--overwrite", is_flag=True, help="replace a video (and its ground truth and actions) already at --out")
@click.option("--quiet", is_flag=True, help="no progress bar")
def make_video(env, out, frames, fps, resolution, spp, domain, params, effect, camera, mesh, seed, overwrite, quiet):
    """Simulate ENV and render a reference video with a random look, plus <out>.truth.json and <out>.actions.csv."""
    from risp_tasks.tasks.reference import ReferenceConfig, make_reference, outside_warning

    cfg = ReferenceConfig(env=env, out=out, frames=frames, fps=fps, resolution=resolution, spp=spp, domain=domain,
                          params=params, effect=effect, camera=camera, mesh=mesh, seed=seed, progress=not quiet,
                          overwrite=overwrite)
    with _memory_hint(f"making {out}", "lower --frames, --resolution or --spp"):
        truth = make_reference(cfg)
    actions = f", actions {truth['actions_path']}" if truth.get("actions_path") else ""
    click.echo(f"wrote {out} ({frames} frames, {resolution}×{resolution}, {fps:g} fps), ground truth "
               f"{truth['truth_path']}{actions}")
    warning = outside_warning(truth["outside_sampled_states"])
    if warning:
        click.echo(warning, err=True)


# ---- BEGIN table command (owned by risp_tasks/tables; docs/tables.md) ----------------------------------------
@cli.command()
@click.option("--table", "table", required=True,
              help="estimation | sysid | imitation | control (the paper's); regularizers (the regularizer "
                   "comparison, every system) | sampling (the rod's temporal-sampling ablation)")
@click.option("--preset", default="cpu", show_default=True, help="cpu (this machine) | paper (a GPU machine)")
@click.option("--repeats", type=int, default=4, show_default=True, help="random looks / initial guesses per cell")
@click.option("--quick", is_flag=True, help="smoke version: tiny data, 1 epoch, 3 iterations (minutes)")
@click.option("--out", default="tables", show_default=True, help="folder of the tables, data sets and networks")
@click.option("--envs", default=None, help="comma-separated environments (default: all; --table sampling: rod)")
@click.option("--methods", default=None, help="comma-separated rows: methods / regularizers / sampling schemes "
              "(default: all; docs/tables.md)")
@click.option("--reg", default=None, help="regularizer of `ours` [default: risp-train's, else surrogate]")
@click.option("--perceptual-weights", default=None, help="local torchvision vgg16 state dict for `perceptual` "
              "(default: the built-in filter bank)")
@click.option("--n-train", type=int, default=None, help="training samples per environment [preset]")
@click.option("--n-test", type=int, default=None, help="target-domain test images per repeat [preset]")
@click.option("--iterations", type=int, default=None, help="optimisation iterations [preset]")
@click.option("--control-start", default=None, help="control: where the optimisers start, neutral (the `average` "
              "row's actions) | random [default: neutral]")
@click.option("--residual", type=click.Choice(("l2", "l1")), default=None,
              help="sysid/imitation/control: residual norm of the render, state and oracle losses [default: l2, "
              "the paper's; risp-task sysid's own default is l1]")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--executor", type=click.Choice(("local", "ray")), default="local", show_default=True,
              help="ray: cells as Ray tasks (optional extra risp[ray])")
@click.option("--jobs", type=int, default=0, show_default=True,
              help="local: cells computed at once, one single-threaded process each (0: one per available CPU)")
@click.option("--quiet", is_flag=True, help="no progress bar")
@click.pass_context
def table(ctx, table, preset, repeats, quick, out, envs, methods, reg, perceptual_weights, n_train, n_test, iterations,
          control_start, residual, seed, executor, jobs, quiet):
    """One of the paper's tables: every method on every environment, mean ± std over repeats (resumable)."""
    from risp_tasks.tables.config import make_config
    from risp_tasks.tables.grid import run_table

    _refuse_unread(ctx, table)

    def names(value):
        return None if value is None else tuple(v.strip() for v in value.split(",") if v.strip())

    cfg = make_config(table, preset=preset, quick=quick, out=out, repeats=repeats, envs=names(envs),
                      methods=names(methods), reg=reg, perceptual_weights=perceptual_weights, n_train=n_train,
                      n_test=n_test, iterations=iterations, control_start=control_start, residual=residual, seed=seed,
                      executor=executor, jobs=jobs, progress=not quiet)
    with _memory_hint(f"computing the {table} table", "use fewer --jobs, a smaller --n-train, or --preset cpu"):
        report = run_table(cfg, echo=click.echo)
    with open(report["files"][0]) as f:
        click.echo(f.read())
    click.echo(f"wrote {report['files'][0]} and {report['files'][1]}")
    failed = report.get("failed_cells") or []
    if failed:
        from risp_data.errors import RispError

        shown = ", ".join(failed[:5]) + (f" and {len(failed) - 5} more" if len(failed) > 5 else "")
        raise RispError(f"{len(failed)} cell(s) failed ({shown}): N/A in the table, their tracebacks in "
                        f"{report['files'][0]}; the same command retries them")


def _refuse_unread(ctx: click.Context, table: str) -> None:
    """Options given on the command line that ``--table`` never reads (tables.grid.UNUSED_BY: e.g. --n-test for the
    task tables, --control-start outside control) are refused in one line: they were dropped without a word.
    Defaults are not "given" (click's parameter source tells them apart)."""
    from click.core import ParameterSource

    from risp_data.errors import RispError
    from risp_tasks.tables.grid import UNUSED_BY

    unread = UNUSED_BY.get(table, ())  # an unknown --table: make_config names the choices
    given = [p.opts[0] for p in ctx.command.params
             if p.name in unread and ctx.get_parameter_source(p.name) is ParameterSource.COMMANDLINE]
    if given:
        raise RispError(f"{', '.join(given)}: not read by --table {table} (docs/tables.md); leave "
                        f"{'it' if len(given) == 1 else 'them'} out")
# ---- END table command ---------------------------------------------------------------------------------------


def main():
    run_cli(cli)


if __name__ == "__main__":
    main()
