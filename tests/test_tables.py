"""risp-task table (risp_tasks/tables): every method on a tiny configuration, resume, bad input.

The configurations are tiny (8 training samples, 2 test images, 1 epoch, 1–2 iterations): these tests check
the machinery and that each method does what it says, not accuracy (docs/RESULTS.md holds the real tables).
Data sets and networks are shared by the tests of this module through one cache folder.
"""

import json
import math
import os
import sys

import pytest
import torch
from click.testing import CliRunner

from risp_data.errors import RispError
from risp_data.processes import proc_stat
from risp_tasks.tables.config import make_config
from risp_tasks.tables.grid import Cell, cell_path, run_folder, run_table
from risp_tasks.tables.methods import METHODS
from risp_tasks.tables.report import markdown
from risp_tasks.tasks.features import VGG_BLOCK, FilterBank, feature_extractor

pytestmark = pytest.mark.timeout(300)

TINY = dict(n_train=8, n_test=2, iterations=2, spp=1, width=4, epochs=1, batch_size=4, frames=3, repeats=1, progress=False)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield str(tmp_path_factory.mktemp("cache"))
    torch.set_num_threads(threads)  # the next modules run with the threads they had


def _cells(report, env):
    return report["cells"][env]


def test_every_method_estimation(cache, tmp_path):
    cfg = make_config("estimation", quick=True, out=str(tmp_path), envs=("cube",), **TINY)
    report = run_table(cfg, cache=cache, echo=lambda *_: None)
    cells = _cells(report, "cube")
    assert set(cells) == set(METHODS)
    for m, entry in cells.items():
        if m == "ours-state":  # in estimation it would be `ours` again: N(I) itself
            assert "is `ours`" in entry["na"], entry
            continue
        assert "na" not in entry, (m, entry)
        assert math.isfinite(entry["mean"]) and entry["n"] == 1
    assert cells["oracle"]["mean"] == 0.0
    assert cells["average"]["mean"] > 0
    # the optimising methods moved away from their start (the average state) and the two networks differ in
    # nothing but the regularizer: their runs are two different checkpoints
    assert cells["pixelwise"]["mean"] != cells["average"]["mean"]
    assert cells["perceptual"]["mean"] != cells["average"]["mean"]
    assert report["perceptual_extractor"] == "filterbank"
    runs = sorted(os.listdir(os.path.join(cache, "runs")))
    assert cfg.reg != "none" and any("-none-" in r for r in runs) and any(f"-{cfg.reg}-" in r for r in runs)
    # each network row read its own network: `ours` the regularized one, `ours-no-grad` the one trained without
    for method, reg in (("ours", cfg.reg), ("ours-no-grad", "none")):
        cell = json.load(open(cell_path(run_folder(cfg), Cell("cube", method, 0))))
        assert f"-{reg}-" in os.path.basename(os.path.dirname(cell["model"])), (method, cell["model"])
    for r in runs:  # trained from memory (a fixed sample order) on one thread, like every cell
        run_cfg = json.load(open(os.path.join(cache, "runs", r, "config.json")))
        assert run_cfg["cache"] == "memory" and run_cfg["threads"] == 1, (r, run_cfg["cache"], run_cfg["threads"])
    md = open(report["files"][0]).read()
    assert "| oracle | 0 ± 0 |" in md and "filterbank" in md
    # per state group in its unit (issue 8): the cube's position [m] and geodesic attitude [deg]
    groups = report["groups"]
    assert set(groups) == {"cube position [m]", "cube attitude [deg]"}
    assert groups["cube attitude [deg]"]["oracle"]["mean"] == pytest.approx(0.0, abs=1e-4)
    assert groups["cube attitude [deg]"]["average"]["mean"] > 1.0  # degrees, not radians or an L1
    assert "| method | cube position [m] | cube attitude [deg] |" in md


def test_every_method_sysid_and_imitation(cache, tmp_path, monkeypatch):
    import risp_tasks.tasks.run as task_run

    residuals, real = [], task_run.run_task
    monkeypatch.setattr(task_run, "run_task",
                        lambda tcfg, **kw: residuals.append((tcfg.loss, tcfg.residual)) or real(tcfg, **kw))
    cfg = make_config("sysid", quick=True, out=str(tmp_path), envs=("cube",), **TINY)
    report = run_table(cfg, cache=cache, echo=lambda *_: None)
    # by default every cell keeps the squared residual the tables were made with (sysid's own default is l1)
    assert len(residuals) == len(METHODS) and {r for _, r in residuals} == {"l2"}, residuals
    assert "- Residual of the network-space losses: `l2`" in open(report["files"][0]).read()
    cells = _cells(report, "cube")
    for m in METHODS:
        assert "na" not in cells[m] and math.isfinite(cells[m]["mean"]), (m, cells[m])
    assert report["perceptual_extractor"] == "filterbank"  # the perceptual cells ran the tasks' perceptual loss
    # average = middle of the range, no optimisation: |0.5·(low+high) − truth| for log10 k_n in [5.5, 6.5)
    from risp_tasks.tables.artifacts import Artifacts

    truth = json.load(open(Artifacts(cfg, cache).video("cube", 0)["truth"]))["params"]["log10_kn"]
    assert cells["average"]["mean"] == pytest.approx(abs(6.0 - truth), abs=1e-9)
    # ours-state fitted the simulation to N's readings (the state loss), so it moved off its random start
    assert cells["ours-state"]["mean"] != cells["random"]["mean"]
    cfg = make_config("imitation", quick=True, out=str(tmp_path), envs=("cube",), **TINY)
    cells = _cells(run_table(cfg, cache=cache, echo=lambda *_: None), "cube")
    assert all(e["na"] == "the cube has no actions" for e in cells.values())
    # --residual l1: the network-space losses (render, state, oracle) take it, the image losses stay squared,
    # in a folder of its own
    residuals.clear()
    cfg = make_config("sysid", quick=True, out=str(tmp_path), envs=("cube",), residual="l1",
                      methods=("ours", "ours-state", "pixelwise", "oracle"), **TINY)
    l1 = run_table(cfg, cache=cache, echo=lambda *_: None)
    assert sorted(residuals) == [("oracle", "l1"), ("pixelwise", "l2"), ("render", "l1"), ("state", "l1")], residuals
    assert l1["folder"] != report["folder"] and "- Residual of the network-space losses: `l1`" in open(l1["files"][0]).read()


def test_the_residual_is_in_the_key_of_the_task_tables_only_when_not_l2(monkeypatch, tmp_path):
    """The default l2 is not in a key (an l2 table's key did not change when --residual came); l1 changes
    sysid/imitation/control's only."""
    from risp_tasks.tables import grid

    keyed, real = [], grid.checksum
    monkeypatch.setattr(grid, "checksum", lambda d: keyed.append(set(d)) or real(d))
    for table in ("estimation", "sysid", "imitation", "control", "regularizers"):
        folders = {r: run_folder(make_config(table, out=str(tmp_path), residual=r)) for r in ("l2", "l1")}
        assert ("residual" in keyed[-1]) == (table in ("sysid", "imitation", "control")), table
        assert "residual" not in keyed[-2], table
        assert (folders["l1"] != folders["l2"]) == (table in ("sysid", "imitation", "control")), table


def test_imitation_runs_on_an_actuated_system(cache, tmp_path):
    cfg = make_config("imitation", quick=True, out=str(tmp_path), envs=("rod",),
                      methods=("average", "random", "pixelwise", "ours", "oracle"), **TINY)
    cells = _cells(run_table(cfg, cache=cache, echo=lambda *_: None), "rod")
    for m, entry in cells.items():
        assert "na" not in entry and math.isfinite(entry["mean"]) and entry["mean"] > 0, (m, entry)
    # the optimising rows start from the `random` row's actions (the seeded random guess): the oracle's iterations,
    # against the true states, bring the motion nearer the reference's
    assert cells["oracle"]["mean"] < cells["random"]["mean"], cells


def test_control_reaches_for_the_pictured_state(cache, tmp_path):
    cfg = make_config("control", quick=True, out=str(tmp_path), envs=("rod",), methods=("average", "ours", "oracle"),
                      **TINY)
    report = run_table(cfg, cache=cache, echo=lambda *_: None)
    for m, entry in report["cells"]["rod"].items():
        assert "na" not in entry and math.isfinite(entry["mean"]) and entry["mean"] > 0, (m, entry)
    # the optimising rows start at the neutral actions, where `average` stays: the oracle's iterations moved it
    # closer to the pictured state (a network row may keep its start: the best iterate by its own loss)
    cells = report["cells"]["rod"]
    assert cells["oracle"]["mean"] < cells["average"]["mean"]
    cell = json.load(open(cell_path(report["folder"], Cell("rod", "oracle", 0))))
    assert len(cell["reached"]) == len(cell["goal"]) == 10  # the rod's ten sensor heights


def test_control_optimisers_start_from_the_neutral_actions(cache, tmp_path):
    """--control-start neutral (default): with no iterations every optimising method reaches exactly what `average`
    (the neutral actions) reaches; --control-start random: they start elsewhere.  Only control's key changes."""
    common = dict(quick=True, out=str(tmp_path), envs=("rod",), methods=("average", "oracle"), **{**TINY, "iterations": 0})
    values = {}
    for start in ("neutral", "random"):
        cfg = make_config("control", control_start=start, **common)
        cells = run_table(cfg, cache=cache, echo=lambda *_: None)["cells"]["rod"]
        values[start] = (cells["average"]["mean"], cells["oracle"]["mean"])
    assert values["neutral"][1] == values["neutral"][0]
    assert values["random"][1] != values["random"][0] and values["random"][0] == values["neutral"][0]
    folder = lambda table, start: run_folder(make_config(table, control_start=start, **common))  # noqa: E731
    assert folder("control", "neutral") != folder("control", "random")
    assert folder("sysid", "neutral") == folder("sysid", "random")


def test_regularizer_comparison(cache, tmp_path):
    cfg = make_config("regularizers", quick=True, out=str(tmp_path), envs=("cube",), **dict(TINY, epochs=2))
    assert cfg.methods == ("none", "surrogate", "exact", "stochastic")
    report = run_table(cfg, cache=cache, echo=lambda *_: None)
    for reg in cfg.methods:
        err, sec = report["cells"]["cube"][reg], report["seconds_per_epoch"]["cube"][reg]
        assert math.isfinite(err["mean"]) and sec["mean"] > 0, (reg, err, sec)
        cell = json.load(open(cell_path(report["folder"], Cell("cube", reg, 0))))
        # --quick ramps γ in from the first step (the cube's own start is half the run): both epochs are timed
        assert cell["timed_epochs"] == 2, cell
    # issue 8: per state group in its unit, not only the L1 that mixes metres and radians
    assert set(report["groups"]) == {"cube position [m]", "cube attitude [deg]"}
    for reg in cfg.methods:
        assert math.isfinite(report["groups"]["cube attitude [deg]"][reg]["mean"]), reg
    text = markdown(report)
    assert "| regularizer | cube position [m] | cube attitude [deg] |" in text
    assert "optimisation iterations" not in text  # the regularizer table optimises nothing
    # same data and budget, different regularizers: four different networks
    models = {json.load(open(cell_path(report["folder"], Cell("cube", r, 0))))["model"] for r in cfg.methods}
    assert len(models) == 4
    assert os.path.getsize(os.path.join(report["folder"], "regularizers.png")) > 1000
    with pytest.raises(RispError, match="unknown regularizer 'ours'"):
        make_config("regularizers", methods=("ours",))


def test_regularizer_epoch_time_counts_only_epochs_with_the_regularizer_on():
    """A late start (γ from half the run) must not let the cheap early epochs into the median."""
    from risp_tasks.tables.cells import regularized_epoch_seconds

    history = [{"epoch": e, "seconds": t} for e, t in enumerate([10.0, 20.0, 80.0, 140.0])]
    assert regularized_epoch_seconds(history, {"steps_per_epoch": [5, 5, 5, 5], "gamma_start": 0.5}) == [60.0, 60.0]
    assert regularized_epoch_seconds(history, {"steps_per_epoch": [5, 5, 5, 5], "gamma_start": 0.0}) == [
        10.0, 10.0, 60.0, 60.0]
    # a start inside epoch 1 (step 7 of 20): epoch 1 is partly unregularized, so the window begins at epoch 2
    assert regularized_epoch_seconds(history, {"steps_per_epoch": [5, 5, 5, 5], "gamma_start": 0.35}) == [60.0, 60.0]
    # a resumed run restarts its clock: the negative difference is dropped, the next epochs count
    resumed = [{"epoch": 0, "seconds": 10.0}, {"epoch": 1, "seconds": 20.0}, {"epoch": 2, "seconds": 5.0},
               {"epoch": 3, "seconds": 65.0}]
    assert regularized_epoch_seconds(resumed, {"steps_per_epoch": [5, 5, 5, 5], "gamma_start": 0.5}) == [60.0]


def test_rod_temporal_sampling_ablation(cache, tmp_path):
    from risp_tasks.tables.sampling import SCHEMES, scheme_frames

    assert scheme_frames("every-5th", 11) == [0, 5, 10] and scheme_frames("first-middle", 11) == [0, 5]
    cfg = make_config("sampling", quick=True, out=str(tmp_path), **TINY)
    assert cfg.envs == ("rod",) and cfg.methods == SCHEMES
    report = run_table(cfg, cache=cache, echo=lambda *_: None)
    cells = [json.load(open(cell_path(report["folder"], Cell("rod", s, 0)))) for s in SCHEMES]
    for c in cells:
        assert len(c["losses"]) == len(c["grid"]) == 5 and min(c["losses"]) > 0
        assert c["value"] == pytest.approx(abs(c["grid"][c["losses"].index(min(c["losses"]))] - c["true"]))
        assert 4 <= c["true"] < 7
    # the schemes see different frames, so their landscapes differ
    assert cells[0]["losses"] != cells[3]["losses"]
    assert os.path.getsize(os.path.join(report["folder"], "sampling.png")) > 1000
    # its key names the sizes it reads: not test images or iterations, which --table sampling refuses as options
    sizes = next(ln for ln in open(report["files"][0]).read().splitlines() if ln.startswith("- Sizes: "))
    assert "test images" not in sizes and "iterations" not in sizes and "video frames" in sizes, sizes


class Killed(Exception):
    pass


def test_killed_and_resumed_run_gives_the_same_table(cache, tmp_path):
    kw = dict(TINY, repeats=2)
    methods = ("average", "random", "ours", "oracle")
    whole = run_table(make_config("estimation", quick=True, out=str(tmp_path / "a"), envs=("cube",),
                                  methods=methods, **kw), cache=cache, echo=lambda *_: None)
    cfg = make_config("estimation", quick=True, out=str(tmp_path / "b"), envs=("cube",), methods=methods, **kw)
    seen = []

    def kill_after_3(cell, result):
        seen.append(cell)
        if len(seen) == 3:
            raise Killed

    with pytest.raises(Killed):
        run_table(cfg, cache=cache, on_cell=kill_after_3, echo=lambda *_: None)
    folder = run_folder(cfg)
    cells = [Cell("cube", m, r) for m in methods for r in range(2)]
    assert sum(os.path.exists(cell_path(folder, c)) for c in cells) == 3
    assert not os.path.exists(os.path.join(folder, "table.json"))
    seen.clear()
    resumed = run_table(cfg, cache=cache, on_cell=lambda c, r: seen.append(c), echo=lambda *_: None)
    assert len(seen) == len(cells) - 3  # only the missing cells ran
    for m in methods:
        a, b = whole["cells"]["cube"][m], resumed["cells"]["cube"][m]
        assert a["values"] == pytest.approx(b["values"], rel=1e-9, abs=1e-12), m
    strip = lambda text: [ln for ln in text.splitlines() if not ln.startswith("- Compute")]  # noqa: E731
    assert strip(open(whole["files"][0]).read()) == strip(open(resumed["files"][0]).read())


def test_quick_networks_reach_the_regularizer():
    """--quick trains a few steps: with the quadrotor's and the cube's late start (half the run) its `ours` was
    `ours-no-grad`'s network. Quick ramps γ in from the first step; the full presets keep the per-environment start."""
    from risp_tasks.tables.artifacts import network_identity, train_config
    from risp_train.config import resolved_gamma_start

    quick = make_config("estimation", quick=True, out="x", envs=("quadrotor",))
    full = make_config("estimation", out="x", envs=("quadrotor",))
    assert resolved_gamma_start(train_config(quick, "reg"), "quadrotor") == 0.0
    assert resolved_gamma_start(train_config(full, "reg"), "quadrotor") == 0.5
    assert train_config(quick, "none").gamma_start == 0.0 and train_config(full, "none").gamma_start is None
    assert network_identity(quick, "quadrotor", "reg") != network_identity(quick, "quadrotor", "none")


def test_a_killed_runs_task_cell_folders_are_removed_by_the_next_run(cache, tmp_path):
    """A task cell works in .tmp-<pid>@<host>-cell-*; a run killed by a signal left them (with a task's inputs in
    them) for good. The next run deletes those of dead processes (and unowned old-style ones), not a live one's."""
    import subprocess
    import sys

    from risp_data.atomic import temp_prefix

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    cfg = make_config("estimation", quick=True, out=str(tmp_path), envs=("cube",), methods=("average",), **TINY)
    host = temp_prefix().split("@")[1]
    left = [tmp_path / f".tmp-{dead_pid}@{host}cell-abc", tmp_path / ".tmp-cell-old"]
    live = tmp_path / f"{temp_prefix()}cell-live"
    for d in (*left, live):
        d.mkdir()
        (d / "goal.json").write_text("{}")
    run_table(cfg, cache=str(tmp_path), echo=lambda *_: None)
    assert not any(d.exists() for d in left) and (live / "goal.json").exists()


def test_a_subset_run_keeps_the_rows_earlier_runs_finished_in_the_shared_table(cache, tmp_path):
    """The folder's table.md is the folder's: a later run with fewer --methods still shows the rows the first one
    finished there (same numbers, no cell recomputed); a row without all the repeats is not shown."""
    kw = dict(TINY, repeats=2, out=str(tmp_path / "t"), envs=("cube",))
    first = run_table(make_config("estimation", quick=True, methods=("average", "random"), **kw), cache=cache,
                      echo=lambda *_: None)
    seen = []
    later = run_table(make_config("estimation", quick=True, methods=("oracle",), **kw), cache=cache,
                      on_cell=lambda c, r: seen.append(c), echo=lambda *_: None)
    assert [c.method for c in seen] == ["oracle", "oracle"]  # only the new row was computed
    assert later["config"]["methods"] == ["average", "random", "oracle"]  # the usual order
    # config.json describes the folder's table.md (all three rows), not the last run's subset
    saved = json.load(open(os.path.join(later["folder"], "config.json")))
    assert saved["methods"] == ["average", "random", "oracle"] and saved["envs"] == ["cube"]
    assert later["cells"]["cube"]["random"]["values"] == first["cells"]["cube"]["random"]["values"]
    text = open(later["files"][0]).read()
    assert "| average |" in text and "| random |" in text and "| oracle |" in text
    more = run_table(make_config("estimation", quick=True, methods=("oracle",), **dict(kw, repeats=3)), cache=cache,
                     echo=lambda *_: None)  # average and random have 2 of 3 repeats: not shown
    assert more["config"]["methods"] == ["oracle"]


def test_the_widened_report_fills_cells_no_run_computed(tmp_path):
    """Earlier cube × average and rod × random, now a run of cube × oracle: both environments and all three rows
    are shown; the cells no run computed are N/A, so no finished row drops out."""
    import json

    from risp_tasks.tables.grid import NOT_COMPUTED, cell_look, widened

    cfg = make_config("estimation", quick=True, out=str(tmp_path), envs=("cube",), methods=("oracle",), repeats=2)
    folder = run_folder(cfg)
    for env, method in (("cube", "average"), ("rod", "random"), ("cube", "oracle")):
        for r in range(2):
            path = cell_path(folder, Cell(env, method, r))
            os.makedirs(os.path.dirname(path), exist_ok=True)
            with open(path, "w") as f:
                json.dump({"env": env, "method": method, "repeat": r, "value": 0.1 * (r + 1),
                           "look": cell_look(Cell(env, method, r), "estimation")}, f)
    shown, extra = widened(cfg, folder)
    assert shown.envs == ("cube", "rod") and shown.methods == ("average", "random", "oracle")
    na = {(r["env"], r["method"]) for r in extra if r.get("na") == NOT_COMPUTED}
    assert na == {("cube", "random"), ("rod", "average"), ("rod", "oracle")}
    assert sum(1 for r in extra if "value" in r) == 4  # cube × average and rod × random, two repeats each


def test_parallel_cells_give_the_same_table_as_one_process(cache, tmp_path):
    """--jobs 2: cells in two spawned single-threaded processes; every cell's number equals the serial run's."""
    kw = dict(TINY, repeats=2)
    methods = ("average", "random", "ours", "pixelwise", "oracle")
    serial = run_table(make_config("estimation", quick=True, out=str(tmp_path / "a"), envs=("cube",),
                                   methods=methods, **kw), cache=cache, echo=lambda *_: None)
    seen = []
    cfg = make_config("estimation", quick=True, out=str(tmp_path / "b"), envs=("cube",), methods=methods, jobs=2, **kw)
    parallel = run_table(cfg, cache=cache, on_cell=lambda c, r: seen.append(r), echo=lambda *_: None)
    # the pool's processes did the work, never this one; a spawn pool starts its second process on demand, and under
    # load the first may finish the cheap cells before the second has imported torch: one or two pids, both valid
    pids = {r["pid"] for r in seen}
    assert len(seen) == len(methods) * 2 and 1 <= len(pids) <= 2 and os.getpid() not in pids, pids
    for m in methods:
        a, b = serial["cells"]["cube"][m], parallel["cells"]["cube"][m]
        assert a["values"] == pytest.approx(b["values"], rel=1e-6, abs=1e-9), m


_stat = proc_stat  # /proc/<pid>/stat's fields after the command name (state, ppid, …), None when gone


def _running(pid: int) -> bool:
    fields = _stat(pid)
    return fields is not None and fields[0] != "Z"


def _children(pid: int) -> set[int]:
    """Live child processes of ``pid`` started by multiprocessing's spawn (the pool's workers, their data loaders;
    not its resource tracker, which ends when the last holder of its pipe does)."""
    stats = {int(e): _stat(int(e)) for e in os.listdir("/proc") if e.isdigit()}
    out = set()
    for p, f in stats.items():
        if f is not None and f[0] != "Z" and int(f[1]) == pid:
            try:
                with open(f"/proc/{p}/cmdline", "rb") as fh:
                    if b"spawn_main" in fh.read():
                        out.add(p)
            except OSError:
                pass
    return out


def _busy_workers(proc, timeout: float = 120) -> tuple[set[int], set[int]]:
    """A `--jobs 2` table's two worker processes, once a network trains in them (its data loaders, their children,
    are returned too)."""
    import time

    workers: set[int] = set()
    deadline = time.time() + timeout
    while len(workers := _children(proc.pid)) < 2 and time.time() < deadline and proc.poll() is None:
        time.sleep(0.5)
    assert len(workers) >= 2, "the table did not start its two worker processes"
    loaders: set[int] = set()
    deadline = time.time() + timeout
    while not (loaders := set().union(*(_children(w) for w in workers))) and time.time() < deadline:
        time.sleep(0.5)
    return workers, loaders


def _still_running(pids: set[int], seconds: float) -> list[int]:
    """The pids still running after up to ``seconds`` of waiting for them to end."""
    import time

    deadline = time.time() + seconds
    while any(_running(p) for p in pids) and time.time() < deadline:
        time.sleep(0.5)
    return [p for p in pids if _running(p)]


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")
def test_jobs_workers_end_when_the_table_process_is_killed(tmp_path):
    """A `--jobs 2` table killed by SIGKILL (no shutdown) leaves no worker computing on behind it."""
    import signal
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "risp_tasks", "table", "--table", "estimation", "--quick", "--jobs", "2",
           "--envs", "cube,rod", "--out", str(tmp_path), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: set[int] = set()
    loaders: set[int] = set()
    try:
        workers, loaders = _busy_workers(proc)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        alive = _still_running(workers | loaders, 30)
        assert not alive, f"workers {alive} went on after their table process was killed"
    finally:
        if proc.poll() is None:
            proc.kill()
        for w in workers | loaders:  # a failed check must not leave them running
            if _running(w):
                os.kill(w, signal.SIGKILL)


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")
def test_ctrl_c_ends_a_jobs_table_at_once_with_one_line(tmp_path):
    """Ctrl-C (SIGINT to the terminal's process group) on a `--jobs 2` table: the workers stop now, not after the
    cells they compute (minutes each), no worker prints a traceback, and the command says `interrupted` (exit 130)."""
    import signal
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "risp_tasks", "table", "--table", "estimation", "--quick", "--jobs", "2",
           "--envs", "cube,rod", "--out", str(tmp_path), "--quiet"]
    # SIGINT's default action restored: a job started in the background of a non-interactive shell (CI) inherits
    # it ignored, and Python then installs no KeyboardInterrupt handler
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    workers: set[int] = set()
    try:
        workers, _ = _busy_workers(proc)
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 130, (proc.returncode, err)
        assert "Traceback" not in err and "Error: interrupted" in err.splitlines(), err
        assert not _still_running(workers, 15), "workers went on after Ctrl-C"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        for w in workers:
            if _running(w):
                os.kill(w, signal.SIGKILL)


def test_estimation_ours_state_alone_trains_no_network(tmp_path):
    """In estimation `ours-state` is N/A (it would be `ours` again); asked for alone it used to train `ours` first."""
    cfg = make_config("estimation", quick=True, out=str(tmp_path), envs=("cube",), methods=("ours-state",), **TINY)
    report = run_table(cfg, echo=lambda *_: None)
    assert "is `ours`" in report["cells"]["cube"]["ours-state"]["na"]
    assert not (tmp_path / "runs").exists()  # no network, and no training set (with Jacobians) for one
    assert not [d for d in os.listdir(tmp_path / "data") if "-train-" in d]


def test_failed_cell_is_stored_and_retried(cache, tmp_path, monkeypatch):
    from risp_tasks.tables import cells as cells_mod

    cfg = make_config("estimation", quick=True, out=str(tmp_path), envs=("cube",), methods=("average",), **TINY)

    def boom(*a, **k):
        raise RuntimeError("disk on fire")

    monkeypatch.setitem(cells_mod.CELLS, "estimation", boom)
    report = run_table(cfg, cache=cache, echo=lambda *_: None)
    assert report["cells"]["cube"]["average"]["na"] == "failed: RuntimeError: disk on fire"
    assert report["failed_cells"] == ["cube/average/r0"]
    monkeypatch.undo()
    report = run_table(cfg, cache=cache, echo=lambda *_: None)
    assert math.isfinite(report["cells"]["cube"]["average"]["mean"]) and report["failed_cells"] == []


def test_a_table_with_failed_cells_is_written_and_the_command_exits_non_zero(tmp_path, monkeypatch):
    """A cell that raised is N/A in the table (the run goes on), but the command then ends with one error line and
    status 1, so that a script or CI sees it (it exited 0)."""
    import risp_tasks.tables.grid as grid
    from risp_tasks.cli import cli

    md, js = tmp_path / "table.md", tmp_path / "table.json"
    md.write_text("| method | cube |\n")
    js.write_text("{}")
    for failed, status in ((["cube/average/r0", "cube/random/r1"], 1), ([], 0)):
        monkeypatch.setattr(grid, "run_table", lambda cfg, echo: {"files": [str(md), str(js)], "failed_cells": failed})
        r = CliRunner().invoke(cli, ["table", "--table", "estimation", "--quick", "--out", str(tmp_path / "t")])
        assert r.exit_code == status, r.output
        assert "| method | cube |" in r.output and f"wrote {md} and {js}" in r.output
        last = r.output.strip().splitlines()[-1]
        if failed:
            assert last.startswith("Error: 2 cell(s) failed (cube/average/r0, cube/random/r1)") and str(md) in last
        else:
            assert last == f"wrote {md} and {js}"


def test_a_damaged_cell_file_is_computed_again(cache, tmp_path):
    """A cell file that is not a JSON object (cut short, or replaced by something else) used to stop every later run
    of the table with a traceback; it is computed again and replaced."""
    cfg = make_config("estimation", quick=True, out=str(tmp_path), envs=("cube",), methods=("average",), **TINY)
    first = run_table(cfg, cache=cache, echo=lambda *_: None)["cells"]["cube"]["average"]["mean"]
    path = cell_path(run_folder(cfg), Cell("cube", "average", 0))
    for damage in (open(path).read()[:100], "[]"):
        with open(path, "w") as f:
            f.write(damage)
        lines = []
        report = run_table(cfg, cache=cache, echo=lines.append)
        assert "0 of 1 cells done, 1 to run" in lines[0], lines
        assert report["cells"]["cube"]["average"]["mean"] == first
        assert json.load(open(path))["value"] == first
    # a JSON object that cannot be this cell — edited or copied by hand — is computed again too, never averaged:
    # a NaN, a string, a negative error, an integer beyond float, no value, a per-group Infinity, another cell's
    good = json.load(open(path))
    for edit in ({"value": float("nan")}, {"value": "0.5"}, {"value": -7.0}, {"value": 10 ** 400}, {"value": None},
                 {"groups": {"position": {"mean": float("inf"), "std": 0.0}}}, {"method": "ours"}, {"repeat": 3}):
        with open(path, "w") as f:
            json.dump({k: v for k, v in {**good, **edit}.items() if v is not None}, f)
        lines = []
        report = run_table(cfg, cache=cache, echo=lines.append)
        assert "0 of 1 cells done, 1 to run" in lines[0], (edit, lines)
        assert report["cells"]["cube"]["average"]["mean"] == first and json.load(open(path))["value"] == first


def test_a_damaged_cached_network_ends_the_run_with_one_line(cache, tmp_path):
    """A cached network that cannot be loaded made every cell reading it fail, on every run, with exit 0."""
    import shutil

    from risp_tasks.tables.artifacts import Artifacts

    cfg = make_config("estimation", quick=True, out=str(tmp_path), envs=("cube",), methods=("ours",), **TINY)
    model = Artifacts(cfg, cache).network("cube", "reg")
    copy = str(tmp_path / "cache")
    shutil.copytree(cache, copy, ignore=shutil.ignore_patterns("estimation-*"))  # the module's cache stays whole
    damaged = model.replace(cache, copy)
    with open(damaged, "r+b") as f:
        f.truncate(os.path.getsize(damaged) // 2)
    with pytest.raises(RispError, match=rf"delete {os.path.dirname(damaged)} to train it again"):
        run_table(cfg, cache=copy, echo=lambda *_: None)
    assert not os.path.exists(cell_path(run_folder(cfg), Cell("cube", "ours", 0)))


def test_two_seeds_share_no_repeat_and_seed_0_keeps_its_data():
    """Repeat k is seeded seed·1000 + k: with `seed + k` the repeats of --seed 1 were --seed 0's shifted by one (the
    same videos, test images and guesses); --seed 0's repeats keep the seeds (and cached files) they had."""
    from risp_tasks.tables.artifacts import TEST_SEED, Artifacts
    from risp_tasks.tables.config import repeat_seed

    seeds = {s: {repeat_seed(s, k) for k in range(4)} for s in (0, 1, 2)}
    assert seeds[0] == {0, 1, 2, 3} and not seeds[0] & seeds[1] and not seeds[1] & seeds[2]
    videos = {s: [Artifacts(make_config("sysid", out="x", seed=s), None).video_config("cube", k) for k in range(4)]
              for s in (0, 1)}
    assert [ref.seed for ref, _ in videos[0]] == [TEST_SEED + k for k in range(4)]
    assert not {p for _, p in videos[0]} & {p for _, p in videos[1]}


def test_the_key_holds_only_what_a_table_reads_and_the_task_defaults():
    """--n-test is not read by the task tables, --iterations not by `regularizers`: neither moves those tables to a
    new folder; both move `estimation`.  The task tables' keys hold the TaskConfig defaults their cells rely on."""
    from risp_tasks.tables import grid

    def moved(table, **kw):
        return run_folder(make_config(table, out="x")) != run_folder(make_config(table, out="x", **kw))

    assert moved("estimation", n_test=32) and moved("estimation", iterations=10)
    assert not moved("sysid", n_test=32) and moved("sysid", iterations=10)
    assert not moved("regularizers", iterations=10) and moved("regularizers", n_test=32)
    assert not moved("sampling", n_test=32) and not moved("regularizers", reg="surrogate")
    keyed = []
    real = grid.checksum
    try:
        grid.checksum = lambda d: keyed.append(d) or real(d)
        run_folder(make_config("sysid", out="x"))
        run_folder(make_config("estimation", out="x"))
    finally:
        grid.checksum = real
    assert keyed[0]["task_defaults"]["lr"] == 3e-3 and keyed[0]["task_defaults"]["fit_initial_state"] is None
    assert set(keyed[0]["task_defaults"]) == set(grid.TASK_DEFAULTS) and "task_defaults" not in keyed[1]


@pytest.mark.parametrize("args, message", [
    (["--table", "lighting"], "Error: unknown table 'lighting'; choose one of: estimation, sysid, imitation, control"),
    (["--table", "estimation", "--methods", "average,magic"], "Error: unknown method 'magic'"),
    (["--table", "estimation", "--envs", "cube,mars"], "Error: unknown environment 'mars'"),
    (["--table", "estimation", "--preset", "tpu"], "Error: unknown preset 'tpu'; choose one of: cpu, paper"),
    (["--table", "estimation", "--reg", "none"], "Error: the regularizer of `ours` must be one of"),
    (["--table", "estimation", "--jobs", "-1"], "Error: --jobs must be >= 0"),
    (["--table", "control", "--control-start", "far"], "Error: unknown control start 'far'; choose one of: neutral"),
    (["--table", "control", "--envs", ""], "Error: --envs is empty: name at least one"),
    (["--table", "control", "--envs", "hand,hand"], "Error: --envs names an entry twice: hand,hand"),
    (["--table", "sysid", "--methods", "ours,ours"], "Error: --methods names an entry twice: ours,ours"),
    (["--table", "sysid", "--repeats", "1001"], "Error: --repeats must be <= 1000"),
    (["--table", "sampling", "--envs", "rod,cube"], "Error: --table sampling is the rod's temporal-sampling ablation"),
    (["--table", "estimation", "--perceptual-weights", "/nonexistent/vgg.pth"],
     "Error: /nonexistent/vgg.pth: perceptual weights file not found"),
])
def test_bad_input_is_one_error_line(tmp_path, args, message):
    from risp_tasks.cli import cli

    r = CliRunner().invoke(cli, ["table", *args, "--out", str(tmp_path / "t")])
    assert r.exit_code == 1
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(message), r.output
    assert not os.path.exists(tmp_path / "t")


@pytest.mark.parametrize("args, refused", [
    (["--table", "estimation", "--control-start", "random"], "--control-start"),
    (["--table", "sysid", "--n-test", "3"], "--n-test"),
    (["--table", "regularizers", "--reg", "surrogate", "--iterations", "5"], "--reg, --iterations"),
    (["--table", "sampling", "--residual", "l2"], "--residual"),  # given, even at its default value
])
def test_options_the_table_never_reads_are_refused_when_given(tmp_path, monkeypatch, args, refused):
    """They were dropped without a word (the table ran as if they were not there); left at their defaults they
    are no error (run_table is reached)."""
    import risp_tasks.tables.grid as grid
    from risp_tasks.cli import cli

    class Reached(Exception):
        pass

    def reached(*a, **k):
        raise Reached

    monkeypatch.setattr(grid, "run_table", reached)  # computing no table
    r = CliRunner().invoke(cli, ["table", *args, "--out", str(tmp_path / "t")])
    lines = r.output.strip().splitlines()
    assert r.exit_code == 1 and len(lines) == 1, r.output
    assert lines[0] == f"Error: {refused}: not read by --table {args[1]} (docs/tables.md); leave " \
                       f"{'them' if ',' in refused else 'it'} out", r.output
    assert not os.path.exists(tmp_path / "t")
    r = CliRunner().invoke(cli, ["table", *args[:2], "--out", str(tmp_path / "t")])
    assert isinstance(r.exception, Reached), r.output  # left at their defaults, the options pass the check


def test_cli_writes_and_prints_the_table(tmp_path):
    from risp_tasks.cli import cli

    r = CliRunner().invoke(cli, ["table", "--table", "control", "--envs", "cube", "--quick", "--repeats", "1",
                                 "--out", str(tmp_path), "--quiet"])
    assert r.exit_code == 0, r.output
    assert "| average | N/A [1] | not found |" in r.output and "- [1] N/A: the cube has no actions" in r.output
    written = r.output.strip().splitlines()[-1]
    assert written.startswith("wrote ") and written.endswith("table.json")
    report = json.load(open(written.split(" and ")[1]))
    assert report["cells"]["cube"]["ours"] == {"na": "the cube has no actions", "n_na": 1, "n": 1, "paper": None}


RAY_TABLE_DRIVER = """
import json, os, sys
import ray
from risp_tasks.tables.config import make_config
from risp_tasks.tables.grid import run_table
kw, cache, out = json.loads(sys.argv[1]), sys.argv[2], sys.argv[3]
ray.init(num_cpus=2, include_dashboard=False)
try:
    report = run_table(make_config("control", out=out, **kw), cache=cache, echo=lambda *_: None)
finally:
    ray.shutdown()
json.dump({"pid": os.getpid(), "cells": report["cells"]}, open("driver.json", "w"))
"""


@pytest.mark.timeout(600)  # above the driver's own 240 s and the serial recompute (the module's 300 s is not)
def test_ray_executor_runs_cells_as_ray_tasks(cache, tmp_path, ray_env):
    """Where Ray is installed (the dev install brings its core): every cell — the rod's computed ones and the cube's
    N/A ones — ran in a Ray worker (its recorded pid is not the driver's: no silent local fallback), and the rod's
    cells agree with the serial runner's. The driver runs in its own process (Ray's threads stay out of the
    suite's, a hang fails at the timeout) on a 2-CPU local cluster, with the run folder given relative to its
    working folder, which Ray's workers do not share (they are given absolute paths)."""
    pytest.importorskip("ray")
    import subprocess

    methods = ("average", "ours-state")
    kw = dict(TINY, quick=True, envs=["cube", "rod"], methods=list(methods), executor="ray")
    r = subprocess.run([sys.executable, "-c", RAY_TABLE_DRIVER, json.dumps(kw), os.path.abspath(cache), "ray"],
                       cwd=tmp_path, env=ray_env, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-3000:]
    driver = json.load(open(tmp_path / "driver.json"))
    cells = driver["cells"]
    assert all(e["na"] == "the cube has no actions" for e in cells["cube"].values())
    cfg = make_config("control", out=str(tmp_path / "ray"), **{k: (tuple(v) if isinstance(v, list) else v)
                                                                for k, v in kw.items()})
    folder = run_folder(cfg)  # the relative --out resolved against the driver's folder, not the workers'
    assert os.path.isfile(os.path.join(folder, "table.json"))
    for env_name in ("cube", "rod"):
        for m in methods:
            cell = json.load(open(cell_path(folder, Cell(env_name, m, 0))))
            assert cell["pid"] != driver["pid"], (env_name, m)
    serial = run_table(make_config("control", quick=True, out=str(tmp_path / "serial"), envs=("rod",),
                                   methods=methods, **TINY), cache=cache, echo=lambda *_: None)
    for m in methods:
        assert cells["rod"][m]["mean"] == pytest.approx(serial["cells"]["rod"][m]["mean"], rel=1e-9), m


def test_ray_executor_without_ray_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError, whether installed or not
    cfg = make_config("control", quick=True, out=str(tmp_path), envs=("rod",), executor="ray", **TINY)
    with pytest.raises(RispError, match=r"pip install 'risp\[ray\]'"):
        run_table(cfg, echo=lambda *_: None)


def test_feature_extractors(tmp_path):
    x = torch.rand(2, 16, 16, 3, dtype=torch.float64, requires_grad=True)
    fb = feature_extractor(None)
    assert isinstance(fb, FilterBank)
    assert torch.equal(fb(x), fb(x))
    assert torch.autograd.gradcheck(lambda i: fb(i)[:, ::97], (x,))
    # a local VGG-16 state dict (torchvision's key names) is loaded and used
    gen = torch.Generator().manual_seed(0)
    state, i = {}, 0
    for spec in VGG_BLOCK:
        if spec != "pool":
            state[f"features.{i}.weight"] = torch.randn(spec[1], spec[0], 3, 3, generator=gen) * 0.1
            state[f"features.{i}.bias"] = torch.zeros(spec[1])
            i += 2
        else:
            i += 1
    state["classifier.0.weight"] = torch.zeros(1)
    path = tmp_path / "vgg16.pth"
    torch.save(state, path)
    vgg = feature_extractor(str(path))
    assert vgg.name == "vgg16-relu2_2"
    assert torch.equal(vgg.features[0].weight, state["features.0.weight"])
    assert vgg(x.float().detach()).shape == (2, 128 * 8 * 8)
    dark = x.float().detach().clone()  # an exactly black (or negative) pixel has a finite gradient, not NaN
    dark[0, :4, :4] = 0.0
    dark[1, :2, :2] = -0.01
    dark.requires_grad_(True)
    vgg(dark).square().sum().backward()
    assert torch.isfinite(dark.grad).all() and dark.grad.abs().sum() > 0
    (tmp_path / "bad.pth").write_bytes(b"not a state dict")
    with pytest.raises(RispError, match="bad.pth: not a torchvision vgg16 state dict"):
        feature_extractor(str(tmp_path / "bad.pth"))
    with pytest.raises(RispError, match="missing.pth: perceptual weights file not found"):
        feature_extractor(str(tmp_path / "missing.pth"))


def test_ours_is_trained_with_risp_trains_default_regularizer():
    # `ours` follows `risp-train fit`'s default (the calibrated one), not the TrainConfig dataclass's `none`
    from risp_train.config import DEFAULT_REG

    assert DEFAULT_REG != "none"
    assert make_config("estimation").reg == DEFAULT_REG
    assert make_config("sysid", reg="exact").reg == "exact"


def test_a_new_default_gamma_is_a_new_network(monkeypatch):
    """The tables find networks again by checksum: a changed per-environment γ default (GAMMA_DEFAULTS) must not
    find the network trained with the old one (the training config stores gamma=None, i.e. "the default")."""
    from risp_tasks.tables.artifacts import network_key
    from risp_train import config as train_config

    tcfg = train_config.make_config("s", "", preset="cpu", reg="stochastic")
    before = network_key(tcfg, "cube", "data")
    assert network_key(tcfg, "cube", "data") == before  # found again
    monkeypatch.setitem(train_config.GAMMA_DEFAULTS, "cube", train_config.GAMMA_DEFAULTS["cube"] + 0.1)
    assert network_key(tcfg, "cube", "data") != before
    moved = network_key(tcfg, "cube", "data")
    monkeypatch.setitem(train_config.GAMMA_START_DEFAULTS, "cube", 0.25)  # the ramp's start is part of it too
    assert network_key(tcfg, "cube", "data") != moved
    assert network_key(train_config.with_(tcfg, reg="none"), "cube", "data") != before
    from risp_train import model as train_model  # the automatic stem's rule is part of the architecture

    monkeypatch.setattr(train_model, "MIN_LAST_MAP", 2)
    assert network_key(tcfg, "cube", "data") != moved


def test_how_a_network_is_computed_is_not_part_of_its_key():
    """Options that change where or how a fit runs, not the network it makes, keep the tables' cached networks
    (and their cells) valid: a new such option (--rank-check) must not retrain every cached network."""
    from risp_tasks.tables.artifacts import network_key
    from risp_train import config as train_config

    tcfg = train_config.make_config("s", "", preset="cpu", reg="stochastic")
    key = network_key(tcfg, "cube", "data")
    for change in (dict(rank_check="resync"), dict(workers=0), dict(threads=1), dict(out="elsewhere")):
        assert network_key(train_config.with_(tcfg, **change), "cube", "data") == key, change


def test_a_revised_motion_is_a_new_reference_video(monkeypatch, tmp_path):
    """A table finds a cached reference video by checksum; a motion's revision (MOTION_REVISIONS, e.g. the cube's
    tosses kept inside the sampled box) is part of it, so a video of the old motion is not found again, while an
    environment whose motion was never revised keeps its key."""
    from risp_tasks.tables.artifacts import Artifacts
    from risp_tasks.tables.config import make_config
    from risp_tasks.tasks import reference

    art = Artifacts(make_config("sysid", out=str(tmp_path)))
    cube, quad = art.video_config("cube", 0)[1], art.video_config("quadrotor", 0)[1]
    assert art.video_config("cube", 0)[1] == cube and art.video_config("cube", 1)[1] != cube
    monkeypatch.setitem(reference.MOTION_REVISIONS, "cube", reference.MOTION_REVISIONS["cube"] + 1)
    assert art.video_config("cube", 0)[1] != cube
    assert art.video_config("quadrotor", 0)[1] == quad
    monkeypatch.setitem(reference.MOTION_REVISIONS, "quadrotor", 2)
    assert art.video_config("quadrotor", 0)[1] != quad


def test_a_revised_motion_recomputes_the_cells_that_read_its_videos(monkeypatch):
    """A finished sysid cell of the cube made before its tosses were revised is computed again; the cube's
    estimation cells (images, no videos) and the other environments' sysid cells are kept."""
    from risp_tasks.tables.grid import Cell, cell_look
    from risp_tasks.tasks import reference

    cube, quad = Cell("cube", "ours", 0), Cell("quadrotor", "ours", 0)
    before = {t: (cell_look(cube, t), cell_look(quad, t)) for t in ("sysid", "estimation")}
    monkeypatch.setitem(reference.MOTION_REVISIONS, "cube", reference.MOTION_REVISIONS["cube"] + 1)
    assert cell_look(cube, "sysid") != before["sysid"][0] and cell_look(quad, "sysid") == before["sysid"][1]
    assert cell_look(cube, "estimation") == before["estimation"][0] == cell_look(cube)


def test_cells_made_with_an_old_network_are_computed_again(cache, tmp_path, monkeypatch):
    """The folder key holds the table's settings, not risp-train's defaults: after a new γ default the `ours` cells
    of a finished table read a new network, so they are computed again; cells that read no network are kept.
    A cell stored without its networks (an older version) counts as not done."""
    from risp_train import config as train_config

    cfg = make_config("estimation", quick=True, out=str(tmp_path), envs=("cube",), methods=("average", "ours"), **TINY)
    first = run_table(cfg, cache=cache, echo=lambda *_: None)
    ours, average = (cell_path(first["folder"], Cell("cube", m, 0)) for m in ("ours", "average"))
    stamp = {p: os.stat(p).st_mtime_ns for p in (ours, average)}
    assert set(json.load(open(ours))["networks"]) == {"reg"} and json.load(open(average))["networks"] == {}
    lines = []
    run_table(cfg, cache=cache, echo=lines.append)  # nothing changed: nothing to run
    assert "2 of 2 cells done, 0 to run" in lines[0], lines
    monkeypatch.setitem(train_config.GAMMA_DEFAULTS, "cube", train_config.GAMMA_DEFAULTS["cube"] + 0.1)
    lines = []
    second = run_table(cfg, cache=cache, echo=lines.append)
    assert second["folder"] == first["folder"] and "1 of 2 cells done, 1 to run" in lines[0], lines
    assert os.stat(average).st_mtime_ns == stamp[average] and os.stat(ours).st_mtime_ns != stamp[ours]
    stored = json.load(open(ours))
    del stored["networks"]
    open(ours, "w").write(json.dumps(stored))
    lines = []
    run_table(cfg, cache=cache, echo=lines.append)
    assert "1 of 2 cells done, 1 to run" in lines[0], lines


def test_a_ctrl_c_inside_drjit_stops_the_table_instead_of_failing_the_cell(tmp_path, monkeypatch):
    """Ctrl-C inside a Dr.Jit loop comes back wrapped (RuntimeError from dr.while_loop); it must end the run like
    a plain KeyboardInterrupt, not be stored as a failed cell while the next one starts."""
    from risp_tasks.tables import cells as cells_mod
    from risp_tasks.tables.grid import compute_cell

    def wrapped(*_args, **_kw):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise RuntimeError("dr.while_loop(): encountered an exception (see above)") from e

    monkeypatch.setitem(cells_mod.CELLS, "estimation", wrapped)
    cfg = make_config("estimation", quick=True, out=str(tmp_path), envs=("cube",), methods=("average",), **TINY)
    with pytest.raises(KeyboardInterrupt):
        compute_cell(cfg, Cell("cube", "average", 0), str(tmp_path / "f"), None)
    assert not os.path.exists(cell_path(str(tmp_path / "f"), Cell("cube", "average", 0)))


def test_perceptual_weights_are_keyed_by_their_contents(tmp_path):
    """A replaced weights file at the same path is another feature extractor (new folder); the same file under
    another path is the same one (same folder)."""
    a, b = tmp_path / "w.pth", tmp_path / "copy" / "w.pth"
    b.parent.mkdir()
    a.write_bytes(b"weights one")
    b.write_bytes(b"weights one")
    folder = lambda path: run_folder(make_config("estimation", out=str(tmp_path), perceptual_weights=str(path)))  # noqa: E731
    first = folder(a)
    assert folder(b) == first
    a.write_bytes(b"weights two")
    assert folder(a) != first
    # tables without a perceptual row: the file does not move them to a new folder (it did, against UNUSED_BY)
    for table in ("regularizers", "sampling"):
        assert run_folder(make_config(table, out=str(tmp_path), perceptual_weights=str(a))) == \
            run_folder(make_config(table, out=str(tmp_path)))


def test_a_data_set_or_network_that_cannot_be_made_ends_a_serial_run(cache, tmp_path, monkeypatch):
    """As with --jobs: each environment's artifacts are made once before its cells (not retried by every cell),
    and a failure there ends the run with its error instead of storing every cell as failed."""
    from risp_tasks.tables import artifacts

    calls = []

    def broken(self, env, which, seed=None):
        calls.append(which)
        raise RispError("the network cannot be trained (test)")

    monkeypatch.setattr(artifacts.Artifacts, "network", broken)
    cfg = make_config("estimation", quick=True, out=str(tmp_path), envs=("cube",), methods=("ours", "ours-no-grad"),
                      **TINY)
    with pytest.raises(RispError, match="cannot be trained"):
        run_table(cfg, cache=cache, echo=lambda *_: None)
    assert len(calls) == 1
    assert not os.path.exists(os.path.join(run_folder(cfg), "cells"))


def test_an_unknown_residual_is_refused_before_anything_is_made(tmp_path):
    from risp_tasks.cli import cli

    r = CliRunner().invoke(cli, ["table", "--table", "sysid", "--residual", "l3", "--out", str(tmp_path / "t")])
    assert r.exit_code == 2 and "Invalid value for '--residual': 'l3' is not one of 'l2', 'l1'" in r.output, r.output
    assert not os.path.exists(tmp_path / "t")
    with pytest.raises(RispError, match="unknown residual 'l3'; choose one of: l2, l1"):
        make_config("sysid", residual="l3")


def test_a_serial_runs_bars_do_not_nest_and_time_only_cells(tmp_path, capsys):
    """A serial run makes the data sets first with their own bars, then starts the cells' bar: nested inside it
    they wrote cursor-movement codes into a log file (stderr not a terminal here), and the cells' time left
    counted the rendering."""
    tiny = dict(TINY, progress=True)
    cfg = make_config("estimation", quick=True, out=str(tmp_path / "t"), envs=("cube",), methods=("average", "random"),
                      **tiny)
    run_table(cfg, cache=str(tmp_path / "cache"), echo=lambda *_: None)
    err = capsys.readouterr().err
    assert "\x1b[A" not in err, "a nested progress bar moved the cursor"
    rendered, first_cell = err.find("render cube/"), err.find("estimation cube/")
    assert 0 <= rendered < first_cell, err[:2000]
    assert err.rfind("render cube/") < first_cell  # no render bar once the cells' bar has started
