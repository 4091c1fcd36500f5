"""The cell grid of a table (environment × method × repeat) and the resumable runner.

    <out>/<table>-<preset>[-quick]-<key>/config.json           the configuration of the table.md beside it
    <out>/<table>-<preset>[-quick]-<key>/cells/<env>/<method>/r<k>.json   one atomic file per finished cell
    <out>/<table>-<preset>[-quick]-<key>/table.md, table.json  the report (report.py)

``<key>`` is the checksum of every setting that changes a cell's number (not of repeats, environments or
methods: adding repeats or methods reuses the finished cells).  A cell whose file exists is never recomputed;
a killed run resumes where it stopped.  A cell that raised is stored with ``failed`` and retried next time.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import traceback
from dataclasses import dataclass, replace
from typing import Callable

from risp_data.atomic import remove_temporaries, write_text_atomic
from risp_data.errors import RispError, message_line
from risp_data.numbers import is_finite_number
from risp_data.processes import end_pool_workers
from risp_data.ray_support import ray_errors, require_ray
from risp_data.shards.manifest import sha256_file

from risp_data.threads import available_cpus

from .artifacts import Artifacts, checksum, prepare
from .config import TableConfig, repeat_seed

#: settings that do not change a cell's number
NOT_IN_KEY = ("out", "repeats", "envs", "methods", "progress", "executor", "workers", "jobs")
#: settings a table never reads (risp_tasks/tables/cells.py, sampling.py): out of its key too, so that changing one
#: does not move the table's finished cells to a new folder
UNUSED_BY = {
    "estimation": ("frames", "control_start", "residual"),
    "sysid": ("n_test", "lr", "control_start"),
    "imitation": ("n_test", "lr", "control_start"),
    "control": ("n_test", "lr"),
    "regularizers": ("frames", "iterations", "lr", "reg", "perceptual_weights", "control_start", "residual"),
    "sampling": ("n_test", "frames", "iterations", "lr", "perceptual_weights", "control_start", "residual"),
}
#: the risp-task options the task tables leave at TaskConfig's defaults (cells._task_run): their values are part of
#: those tables' keys, so that a changed default (as --fit-initial-state's once was) starts a new folder instead of
#: mixing cells made before and after it
TASK_DEFAULTS = ("optimizer", "lr", "momentum", "warm_start", "grow_horizon", "action_knots", "fit_initial_state",
                 "every", "gradient")


@dataclass(frozen=True)
class Cell:
    env: str
    method: str
    repeat: int

    @property
    def name(self) -> str:
        return f"{self.env}/{self.method}/r{self.repeat}"


def grid(cfg: TableConfig) -> list[Cell]:
    """Environment-major order, so each environment's data and networks are made once, early."""
    return [Cell(e, m, r) for e in cfg.envs for m in cfg.methods for r in range(cfg.repeats)]


def run_folder(cfg: TableConfig) -> str:
    skip = NOT_IN_KEY + UNUSED_BY[cfg.table]
    if cfg.residual == "l2":  # the default stays out: --residual's arrival did not change an l2 table's key
        skip += ("residual",)
    settings = {k: v for k, v in cfg.to_dict().items() if k not in skip}
    if cfg.table in ("sysid", "imitation", "control"):
        from dataclasses import fields

        from risp_tasks.tasks.config import TaskConfig

        settings["task_defaults"] = {f.name: f.default for f in fields(TaskConfig) if f.name in TASK_DEFAULTS}
    if (cfg.perceptual_weights and os.path.isfile(cfg.perceptual_weights)  # the file's contents, not its name,
            and "perceptual_weights" not in skip):  # where the table has a perceptual row at all
        settings["perceptual_weights"] = sha256_file(cfg.perceptual_weights)  # a replaced file is another F
    key = checksum(settings)
    return os.path.join(cfg.out, f"{cfg.table}-{cfg.preset}{'-quick' if cfg.quick else ''}-{key}")


def cell_path(folder: str, cell: Cell) -> str:
    return os.path.join(folder, "cells", cell.env, cell.method, f"r{cell.repeat}.json")


def read_cell(path: str, look: str | None = None, networks: dict | None = None) -> dict | None:
    """A finished cell's result, or None when absent, failed, made with another ``look`` of its environment
    (risp_data.envs.look; cells from before looks were recorded count as another look) or with other
    ``networks`` than the table's settings make today (cell_networks; cells from before networks were recorded
    count as other networks): to be (re)computed.  A damaged file (not a JSON object: written by something else, as
    the runner writes atomically) is computed again too, and replaced."""
    result = _load_cell(path)
    if result is None or result.get("unreadable"):
        return None
    if result.get("failed") or (look is not None and result.get("look") != look):
        return None
    if networks and result.get("networks") != networks:
        return None
    return result


def cell_networks(cfg: TableConfig, cell: Cell) -> dict:
    """{role: identity} of the networks a cell reads (artifacts.network_identity), {} for one that reads none.  The
    folder key holds the table's settings, not risp-train's defaults: a changed preset value, γ default or stem rule
    trains a new network, and this makes the cells that read the old one count as not done."""
    from .artifacts import network_identity
    from .methods import estimation_network, get_method

    if cfg.table == "sampling":
        return {"reg": network_identity(cfg, "rod", "reg")} if cell.env == "rod" else {}
    if cfg.table == "regularizers":
        return {cell.method: network_identity(cfg, cell.env, cell.method, seed=repeat_seed(cfg.seed, cell.repeat))}
    if cfg.table == "estimation":
        which = estimation_network(cell.method)
        return {which: network_identity(cfg, cell.env, which)} if which else {}
    which = get_method(cell.method).network
    if cfg.table in ("imitation", "control") and cell.env == "cube":  # N/A: no actions, nothing is read
        return {}
    role = which or "reg"  # a task reads its initial state from the row's network; rows without one use `ours`'
    return {role: network_identity(cfg, cell.env, role)}


def _done(cfg: TableConfig, folder: str, cell: Cell) -> dict | None:
    """The cell's stored result if it counts as finished for ``cfg`` (read_cell), else None."""
    return read_cell(cell_path(folder, cell), cell_look(cell, cfg.table), cell_networks(cfg, cell))


#: tables whose cells read reference videos (risp_tasks.tasks.reference): a revised motion recomputes them
VIDEO_TABLES = ("sysid", "imitation", "control", "sampling")


def cell_look(cell: Cell, table: str | None = None) -> str:
    """What a cell saw of its environment: the look's fingerprint (risp_data.envs.look) and, in a table that reads
    reference videos, the motion's revision where it was revised (reference.MOTION_REVISIONS): a finished cell made
    with another look or motion is computed again."""
    from risp_data.envs.look import look_fingerprint
    from risp_tasks.tasks.reference import MOTION_REVISIONS

    look = look_fingerprint(cell.env)
    if table in VIDEO_TABLES and cell.env in MOTION_REVISIONS:
        look += f"/motion{MOTION_REVISIONS[cell.env]}"
    return look


def compute_cell(cfg: TableConfig, cell: Cell, folder: str, cache: str | None) -> dict:
    """Compute one cell and store it atomically; an exception becomes a stored ``failed`` N/A result."""
    from .cells import CELLS

    started = time.perf_counter()
    try:
        result = CELLS[cfg.table](cfg, Artifacts(cfg, cache), cell.env, cell.method, cell.repeat)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as e:  # noqa: BLE001 - one failing cell must not end a four-hour run
        from risp_data.cli_util import caused_by_interrupt

        if caused_by_interrupt(e):  # Ctrl-C inside Dr.Jit comes back wrapped: it stops the run, not the cell
            raise KeyboardInterrupt from e
        line = message_line(e)
        result = {"na": f"failed: {type(e).__name__}: {line}", "failed": True,
                  "traceback": traceback.format_exc(limit=8)}
    result.update({"table": cfg.table, "env": cell.env, "look": cell_look(cell, cfg.table),
                   "networks": cell_networks(cfg, cell), "method": cell.method,
                   "repeat": cell.repeat, "seed": cfg.seed,
                   "repeat_seed": repeat_seed(cfg.seed, cell.repeat), "seconds": time.perf_counter() - started,
                   "loadavg": list(os.getloadavg()), "pid": os.getpid()})
    write_text_atomic(cell_path(folder, cell), json.dumps(result, indent=1, sort_keys=True) + "\n")
    return result


def run_table(cfg: TableConfig, cache: str | None = None, on_cell: Callable[[Cell, dict], None] | None = None,
              echo: Callable[[str], None] = print) -> dict:
    """Compute every missing cell of ``cfg`` (resuming), then write and return the report."""
    from tqdm.auto import tqdm

    from .report import write_report

    folder = run_folder(cfg)
    if cfg.executor == "ray":  # before anything is written: without the extra the run cannot start
        require_ray()
    os.makedirs(folder, exist_ok=True)
    # a killed run's task-cell folders (.tmp-<pid>@<host>-cell-*): its process is gone; a running one's are kept
    remove_temporaries(Artifacts(cfg, cache).root)
    if not os.path.exists(os.path.join(folder, "config.json")):  # a first run killed before its report has one
        _write_config(cfg, folder)
    cells = grid(cfg)
    todo = [c for c in cells if _done(cfg, folder, c) is None]
    echo(f"{cfg.table}: {len(cells) - len(todo)} of {len(cells)} cells done, {len(todo)} to run; results: {folder}")
    jobs = cfg.jobs or available_cpus()
    if cfg.executor == "ray" and todo:
        _run_ray(cfg, todo, folder, cache, on_cell)
    elif jobs > 1 and len(todo) > 1:
        _run_processes(cfg, todo, folder, cache, on_cell, jobs)
    else:
        with single_threaded():
            # every environment's data sets and networks first (a failure ends the run before any cell), with
            # their own progress bars: inside the cells' bar they would nest, which a log file gets as cursor
            # codes, and the cells' rate and time left would count the hours of rendering and training
            for env in dict.fromkeys(c.env for c in todo):
                prepare(_for_todo(cfg, todo, env), env, cache)
            with tqdm(todo, unit="cell", desc=cfg.table, disable=not cfg.progress) as bar:
                for cell in bar:
                    bar.set_description(f"{cfg.table} {cell.name}")
                    result = compute_cell(cfg, cell, folder, cache)
                    if on_cell is not None:
                        on_cell(cell, result)
    results = [_done(cfg, folder, c) or _failed(folder, c) for c in cells]
    shown, earlier = widened(cfg, folder)
    report = write_report(shown, folder, results + earlier)
    _write_config(shown, folder)  # the configuration of the table.md beside it, not of this run's subset alone
    # this run's cells that raised (stored as N/A with their traceback, retried by the next run): the command
    # writes the table and then exits non-zero, so that a script or CI sees them
    report["failed_cells"] = [c.name for c, r in zip(cells, results) if r.get("failed")]
    return report


def _write_config(cfg: TableConfig, folder: str) -> None:
    write_text_atomic(os.path.join(folder, "config.json"), json.dumps(cfg.to_dict(), indent=1, sort_keys=True) + "\n")


#: the entry of a shown cell that no run computed in the folder
NOT_COMPUTED = "not computed in this folder (run the table with this environment and row)"


def widened(cfg: TableConfig, folder: str) -> tuple[TableConfig, list[dict]]:
    """The report's configuration and the extra results it shows. The folder's table.md is the folder's: a run
    with a subset of --envs/--methods also shows every environment and row that earlier runs finished there
    (with all of this run's repeats), in the usual order; a cell of the widened grid that no run finished is
    shown as N/A (NOT_COMPUTED), never dropped with its row."""
    from risp_data.envs import ENV_NAMES
    from risp_train.regularizers import REGULARIZERS

    from .methods import METHODS
    from .sampling import SCHEMES

    rows = {"regularizers": REGULARIZERS, "sampling": SCHEMES}.get(cfg.table, METHODS)
    requested = {(e, m) for e in cfg.envs for m in cfg.methods}
    found: dict = {}
    for e in ENV_NAMES:
        for m in rows:
            if (e, m) in requested:
                continue
            cells = [_done(cfg, folder, Cell(e, m, r)) for r in range(cfg.repeats)]
            if all(c is not None for c in cells):
                found[(e, m)] = cells
    if not found:
        return cfg, []
    envs = [e for e in ENV_NAMES if e in cfg.envs or any(k[0] == e for k in found)]
    methods = [m for m in rows if m in cfg.methods or any(k[1] == m for k in found)]
    extra = [r for cells in found.values() for r in cells]
    extra += [{"env": e, "method": m, "repeat": 0, "na": NOT_COMPUTED} for e in envs for m in methods
              if (e, m) not in requested and (e, m) not in found]
    return replace(cfg, envs=tuple(envs), methods=tuple(methods)), extra


def _load_cell(path: str) -> dict | None:
    """A cell file's JSON object; None when absent; ``{"na": …, "unreadable": True}`` when damaged."""
    if not os.path.exists(path):
        return None
    try:
        with open(path) as f:
            result = json.load(f)
    except (OSError, ValueError) as e:
        return {"na": f"unreadable cell file {path}: {message_line(e, type(e).__name__)}",
                "unreadable": True}
    if not isinstance(result, dict):
        return {"na": f"unreadable cell file {path}: not a JSON object", "unreadable": True}
    damage = _cell_damage(path, result)
    if damage:
        return {"na": f"damaged cell file {path}: {damage}", "unreadable": True}
    return result


def _cell_damage(path: str, result: dict) -> str | None:
    """Why a cell file's content cannot be the cell at ``path`` (None: it can): the runner writes every cell as one
    atomic file whose env, method and repeat are its path's and whose value is a finite error ≥ 0 (every table's
    metric is one), or a N/A with its reason; anything else was edited or copied by hand and is computed again."""
    parts = os.path.normpath(path).split(os.sep)
    if len(parts) >= 3 and parts[-1].startswith("r") and parts[-1].endswith(".json"):
        own = {"env": parts[-3], "method": parts[-2], "repeat": parts[-1][1:-5]}
        for key, want in own.items():
            if key in result and str(result[key]) != want:
                return f"holds the cell {key}={result[key]!r}, not {want!r}"
    if "na" in result or result.get("failed"):
        return None
    if "value" not in result:
        return "no value"
    value = result["value"]
    if not is_finite_number(value) or value < 0:
        return f"value {str(value)[:30]} is not a finite error >= 0"
    groups = result.get("groups") or {}  # estimation's per-group errors: {group: {mean, std, n, unit}}
    for name, group in (groups.items() if isinstance(groups, dict) else [("groups", groups)]):
        if not isinstance(group, dict) or not all(is_finite_number(group.get(k)) for k in ("mean", "std") if k in group):
            return f"group {name!r} holds a non-finite number"
    return None


def _failed(folder: str, cell: Cell) -> dict:
    """What the report shows of a cell that did not finish: its stored failure (or the damage of its file)."""
    path = cell_path(folder, cell)
    return _load_cell(path) or {"na": f"missing cell file {path}"}


def _single_threaded() -> None:
    """Every cell runs on one torch and one Dr.Jit thread, in this process or in one of ``jobs`` processes: a
    cell's number must not depend on how it was scheduled, and the reverse-mode renders' atomic gradient sums
    change with Dr.Jit's thread count (pixelwise estimates moved by 1 % between 1 and 2 threads)."""
    import drjit as dr
    import torch

    torch.set_num_threads(1)
    dr.set_thread_count(1)


def _pool_worker_init(parent: int) -> None:
    """A ``--jobs`` process: single-threaded (above), and it ends when the table process that started it is gone.
    Killed by a signal, the parent cannot shut its pool down, and the workers would go on computing, unseen,
    beside the next run; a watcher thread ends them (their results are atomic files, so nothing is half-written)."""
    import signal
    import threading

    _single_threaded()
    # Ctrl-C reaches the whole process group: the table process ends its workers itself (_run_processes), and an
    # idle worker interrupted in the pool's queue would print a traceback of its own
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _end_worker)  # end_pool_workers: this worker and its data loaders

    def watch():
        while os.getppid() == parent:
            time.sleep(1.0)
        _end_worker()  # with a training's data loaders, which would outlive it

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _compute_cell_single_threaded(cfg: TableConfig, cell: Cell, folder: str, cache: str | None) -> dict:
    """compute_cell in a Ray worker: single-threaded like every other cell."""
    _single_threaded()
    return compute_cell(cfg, cell, folder, cache)


def _for_todo(cfg: TableConfig, todo: list[Cell], env: str) -> TableConfig:
    """``cfg`` with the rows that still have cells of ``env`` to compute: what prepare makes (no network is trained
    for rows whose cells are all done)."""
    return replace(cfg, methods=tuple(m for m in cfg.methods if any(c.env == env and c.method == m for c in todo)))


def _prepare_single_threaded(cfg: TableConfig, env: str, cache: str | None) -> None:
    """prepare in a Ray worker: single-threaded like the --jobs and serial paths, so that the executor that made a
    data set first does not decide the later cells' numbers."""
    _single_threaded()
    prepare(cfg, env, cache)


@contextlib.contextmanager
def single_threaded():
    """:func:`_single_threaded` for the serial runner, giving the caller's thread counts back afterwards."""
    import drjit as dr
    import torch

    before = torch.get_num_threads(), dr.thread_count()
    _single_threaded()
    try:
        yield
    finally:
        torch.set_num_threads(before[0])
        dr.set_thread_count(before[1])


def _run_processes(cfg: TableConfig, todo: list[Cell], folder: str, cache: str | None, on_cell, jobs: int) -> None:
    """``--jobs N``: N spawned single-threaded processes (concurrent.futures; spawned, so no Dr.Jit/OpenMP thread
    state is forked).  Each environment's artifacts are made by one task (so each is made once), its cells are
    queued when that task has finished: environments' data sets and networks are made side by side, and the
    first environment's cells run while the next one's networks train.  A cell's number does not depend on
    which process computed it or when (each cell is seeded by itself)."""
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    from tqdm.auto import tqdm

    by_env: dict[str, list[Cell]] = {}
    for c in todo:
        by_env.setdefault(c.env, []).append(c)
    quiet = replace(cfg, progress=False)  # progress bars of parallel renders and fits would interleave
    pool = ProcessPoolExecutor(min(jobs, len(todo)), mp_context=mp.get_context("spawn"), initializer=_pool_worker_init,
                               initargs=(os.getpid(),))
    try:
        preparing = {pool.submit(prepare, _for_todo(quiet, todo, env), env, cache): env for env in by_env}
        pending: dict = {}
        with tqdm(total=len(todo), unit="cell", desc=f"{cfg.table} ({jobs} jobs)", disable=not cfg.progress) as bar:
            while preparing or pending:
                done, _ = wait(list(preparing) + list(pending), return_when=FIRST_COMPLETED)
                for future in done:
                    if future in preparing:
                        env = preparing.pop(future)
                        future.result()  # a data set or network that cannot be made ends the run
                        if not pending and bar.n == 0:  # the first cells start: time left is timed from here,
                            bar.reset()                  # not from the rendering and training before them
                        bar.set_description(f"{cfg.table} {env}: data and networks ready")
                        pending.update({pool.submit(compute_cell, cfg, c, folder, cache): c for c in by_env[env]})
                        continue
                    cell = pending.pop(future)
                    result = future.result()
                    bar.set_description(f"{cfg.table} {cell.name} done")
                    bar.update(1)
                    if on_cell is not None:
                        on_cell(cell, result)
    except BrokenProcessPool:
        end_pool_workers(pool)
        raise RispError("a --jobs process died (killed, or out of memory); finished cells are kept: rerun the same "
                        "command to resume, with fewer --jobs if memory is short") from None
    except BaseException:  # Ctrl-C, or an artifact that cannot be made: the cells being computed are dropped
        end_pool_workers(pool)
        raise
    pool.shutdown(wait=True)


def _end_worker(*_) -> None:
    """SIGTERM in a --jobs process: end its own children (a training's data loaders, which would hold the
    terminal's pipes and go on decoding), then itself."""
    import multiprocessing as mp

    for child in mp.active_children():
        child.kill()
    os._exit(1)


def _run_ray(cfg: TableConfig, todo: list[Cell], folder: str, cache: str | None, on_cell) -> None:
    """Each environment's artifacts as one Ray task (so no two tasks make the same one), then every cell as a
    Ray task (a running cluster when RAY_ADDRESS is set, else a local one)."""
    from tqdm.auto import tqdm

    ray = require_ray()
    if not ray.is_initialized():
        ray.init()
    # Ray workers need not share this process's working directory (a cluster's never do): absolute paths
    folder, cache = os.path.abspath(folder), (os.path.abspath(cache) if cache else cache)
    if cfg.perceptual_weights:
        cfg = replace(cfg, perceptual_weights=os.path.abspath(cfg.perceptual_weights))
    remote_prepare = ray.remote(_prepare_single_threaded)
    remote_cell = ray.remote(_compute_cell_single_threaded)
    with ray_errors("making a table's data and networks"):
        ray.get([remote_prepare.remote(_for_todo(cfg, todo, env), env, cache) for env in sorted({c.env for c in todo})])
    pending = {remote_cell.remote(cfg, c, folder, cache): c for c in todo}
    with tqdm(total=len(todo), unit="cell", desc=f"{cfg.table} (ray)", disable=not cfg.progress) as bar:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            cell = pending.pop(done[0])
            with ray_errors(f"cell {cell.name}"):
                result = ray.get(done[0])
            bar.set_description(f"{cfg.table} {cell.name} done")
            bar.update(1)
            if on_cell is not None:
                on_cell(cell, result)
