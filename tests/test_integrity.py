"""Integrity end to end (issue 13): every sample accounted for, nothing overwritten, damaged folders repaired,
user errors as one ``Error:`` line.  Real renders (tiny: 16×16 pixels, 1 spp), real shards, real training.

The kill/resume matrix is in tests/test_kill_matrix.py.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
import tarfile

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from risp_data.cli import cli as data_cli
from risp_data.errors import RispError
from risp_data.shards.manifest import MARKER_DIR, save_manifest
from risp_train.cli import cli as train_cli

RES = 16
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=ROOT)


def _render(out, env="cube", n=16, shard_size=4, res=RES, extra=()):
    cmd = [sys.executable, "-m", "risp_data", "render", "--env", env, "--n", str(n), "--res", str(res), "--spp", "1",
           "--shard-size", str(shard_size), "--workers", "1", "--quiet", "--out", str(out), *extra]
    r = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=600)
    assert r.returncode == 0, r.stderr
    return str(out)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("integrity")
    return {
        "train": _render(root / "train"),
        "quad": _render(root / "other", env="quadrotor", extra=("--format", "wds")),
        "val8": _render(root / "val8", n=8, res=8, extra=("--format", "wds", "--no-jacobian")),
        "root": root,
    }


@pytest.fixture(scope="module")
def model(data):
    """A tiny trained model (one epoch) of the training folder."""
    out = data["root"] / "model-run"
    r = CliRunner().invoke(train_cli, ["fit", data["train"], "--out", str(out), *_TINY, "--epochs", "1"])
    assert r.exit_code == 0, r.output
    return str(out / "model.pt")


_TINY = ("--preset", "cpu", "--width", "4", "--batch-size", "4", "--workers", "0", "--quiet")


def _copy(src, dst):
    shutil.copytree(src, dst)
    return str(dst)


def _manifest(folder):
    with open(os.path.join(folder, "manifest.json")) as f:
        return json.load(f)


def _save_manifest(folder, m):
    with open(os.path.join(folder, "manifest.json"), "w") as f:
        json.dump(m, f)


def _one_line_error(result):
    """A CliRunner result that failed with exactly one ``Error:`` line and no traceback."""
    assert result.exit_code != 0, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(lines) == 1 and "Traceback" not in result.output, result.output
    assert not isinstance(result.exception, Exception) or isinstance(result.exception, SystemExit), result.exception
    return lines[0]


def _zero_tail_at_last_sample(tar_path):
    """What a crash can leave: the tar's last sample overwritten by zeros, file size unchanged."""
    with tarfile.open(tar_path) as tar:
        members = tar.getmembers()
    last_key = members[-1].name.split(".", 1)[0]
    offset = min(m.offset for m in members if m.name.startswith(last_key + "."))
    size = os.path.getsize(tar_path)
    with open(tar_path, "r+b") as f:
        f.seek(offset)
        f.write(bytes(size - offset))
    assert os.path.getsize(tar_path) == size


# ------------------------------------------------------------------------------ 1. fewer samples


def test_a_truncated_shard_in_fit_names_the_repair_that_then_works(data, tmp_path):
    """fit and eval on a cut shard: the one error line ends with the repair command (inspect named it, the readers
    did not), and that command, run as printed, makes the folder trainable again."""
    import shlex

    bad = _copy(data["train"], tmp_path / "cut")
    tar = os.path.join(bad, "wds", "shard-000001.tar")
    with open(tar, "r+b") as f:
        f.truncate(os.path.getsize(tar) // 2)
    runner = CliRunner()
    line = _one_line_error(runner.invoke(train_cli, ["fit", bad, "--out", str(tmp_path / "run"), *_TINY,
                                                     "--format", "wds"]))
    assert "shard-000001.tar" in line and line.endswith(f"repair: risp-data verify --repair {bad}")
    args = shlex.split(line.rsplit("repair: risp-data ", 1)[1])
    r = runner.invoke(data_cli, args + ["--samples", "1"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(train_cli, ["fit", bad, "--out", str(tmp_path / "run"), *_TINY, "--format", "wds",
                                  "--epochs", "1"])
    assert r.exit_code == 0, r.output


def test_zero_filled_tar_tail_is_refused_by_every_reader(data, model, tmp_path):
    from risp_data.shards import iter_wds

    bad = _copy(data["train"], tmp_path / "zero-tail")
    tar = os.path.join(bad, "wds", "shard-000002.tar")
    _zero_tail_at_last_sample(tar)
    with pytest.raises(RispError, match=r"shard-000002\.tar holds 3 samples, the manifest lists 4"):
        list(iter_wds(bad))
    runner = CliRunner()
    line = _one_line_error(runner.invoke(train_cli, ["fit", bad, "--out", str(tmp_path / "run"), *_TINY]))
    assert "shard-000002.tar holds 3 samples" in line
    line = _one_line_error(runner.invoke(train_cli, ["eval", model, bad, "--quiet", "--out", str(tmp_path / "ev")]))
    assert "shard-000002.tar holds 3 samples" in line
    r = runner.invoke(data_cli, ["inspect", bad])
    assert r.exit_code == 1 and "shard 2:" in r.output and "holds 3 samples" in r.output, r.output
    r = runner.invoke(data_cli, ["inspect", data["train"], "--deep"])
    assert r.exit_code == 0 and "4/4 listed shards intact (sizes, sample counts, sha256)" in r.output, r.output


def test_inspect_deep_finds_a_flipped_byte_that_sizes_miss(data, tmp_path):
    bad = _copy(data["train"], tmp_path / "flipped")
    path = os.path.join(bad, "data.zarr", "images", "c", "1", "0", "0", "0")
    raw = bytearray(open(path, "rb").read())
    raw[len(raw) // 2] ^= 0xFF
    open(path, "wb").write(bytes(raw))
    runner = CliRunner()
    assert runner.invoke(data_cli, ["inspect", bad]).exit_code == 0  # same size and count: only hashing sees it
    r = runner.invoke(data_cli, ["inspect", bad, "--deep"])
    assert r.exit_code == 1 and "shard 1:" in r.output and "sha256 differs" in r.output, r.output


def test_eval_and_fit_refuse_an_out_they_cannot_write_before_working(data, model, tmp_path, monkeypatch):
    """An --out under a file: one line naming that file, before any image is evaluated or any data decoded (eval
    found out only after evaluating every image, and said `File exists` of the file)."""
    import risp_train.evaluate as evaluate
    import risp_train.train as train

    blocker = tmp_path / "afile"
    blocker.write_text("x")
    monkeypatch.setattr(evaluate, "iter_batches", lambda *a, **k: pytest.fail("evaluated before checking --out"))
    line = _one_line_error(CliRunner().invoke(train_cli, ["eval", model, data["train"], "--quiet",
                                                          "--out", str(blocker / "ev")]))
    assert f"{blocker} is a file" in line
    monkeypatch.setattr(train, "load_memory_set", lambda *a, **k: pytest.fail("decoded before checking --out"))
    line = _one_line_error(CliRunner().invoke(train_cli, ["fit", data["train"], "--out", str(blocker / "run"), *_TINY,
                                                          "--epochs", "1"]))
    assert f"{blocker} is a file" in line


def test_atomic_write_names_the_file_it_could_not_write(tmp_path):
    """A failure to create the temporary names the file being written, not `.tmp-…`."""
    from risp_data.atomic import atomic_write

    (tmp_path / "afile").write_text("x")
    target = tmp_path / "afile" / "x.json"
    with pytest.raises(OSError) as e:
        with atomic_write(target, "w") as f:
            f.write("{}")
    assert e.value.filename == str(target)


def test_a_killed_tasks_temporary_folder_in_a_run_folder_does_not_stop_fit(data, model, tmp_path):
    """A task or make-video killed while writing its --out inside a run folder leaves a `.tmp-*` folder there
    (temp_folder); `fit --overwrite` deleted the old run and then stopped at it ("Is a directory"), leaving
    neither run.  Temporaries are files and folders alike, and a link among them is removed, not followed."""
    run = tmp_path / "run"
    r = CliRunner().invoke(train_cli, ["fit", data["train"], "--out", str(run), *_TINY, "--epochs", "1"])
    assert r.exit_code == 0, r.output
    (run / ".tmp-k1lled" / "frames").mkdir(parents=True)
    (run / ".tmp-k1lled" / "frames" / "0000.png").write_bytes(b"half")
    keep = tmp_path / "elsewhere"
    keep.mkdir()
    (keep / "mine.txt").write_text("mine")
    os.symlink(keep, run / ".tmp-link")
    r = CliRunner().invoke(train_cli, ["fit", data["train"], "--out", str(run), *_TINY, "--epochs", "1",
                                       "--overwrite", "--seed", "3"])
    assert r.exit_code == 0, r.output
    assert (run / "model.pt").is_file() and not [n for n in os.listdir(run) if n.startswith(".tmp-")]
    assert (keep / "mine.txt").read_text() == "mine"


def test_a_running_jobs_temporaries_survive_a_cleanup_and_a_killed_ones_do_not(tmp_path):
    """remove_temporaries (fit's, render's) deleted every `.tmp-*` in the folder, also the result folder a task
    was still writing there — the task then failed at its final rename.  Temporaries name their writer; a live
    writer's stay, a dead one's and an unowned (older) one go."""
    from risp_data.atomic import remove_temporaries, temp_folder, temp_prefix, temporary_in_use

    mine = temp_folder(tmp_path)  # this process's: alive
    writer = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    theirs = tmp_path / temp_prefix().replace(f"{os.getpid()}@", f"{writer.pid}@")
    theirs.mkdir()
    (theirs / "result.json").write_text("{}")
    (tmp_path / ".tmp-old-style").write_text("half")
    remove_temporaries(tmp_path)
    assert os.path.isdir(mine) and (theirs / "result.json").is_file()
    assert not (tmp_path / ".tmp-old-style").exists()
    writer.communicate(b"")  # the writer ends (and is reaped): now its temporary is a leftover
    assert not temporary_in_use(theirs.name)
    remove_temporaries(tmp_path)
    assert os.path.isdir(mine) and not theirs.exists()
    other_host = tmp_path / f".tmp-{writer.pid}@another_machine-x1"
    other_host.mkdir()  # a shared file system's: its writer cannot be asked, so it stays
    remove_temporaries(tmp_path)
    assert other_host.exists()


def test_a_second_fit_on_a_running_fits_folder_is_refused_and_deletes_nothing(data, tmp_path):
    """Nothing stopped two fits on one run folder: a second `--overwrite` deleted the running one's files and a
    second `--resume` wrote checkpoints into it beside the first.  fit holds the folder's lock from its first write
    to its last (here another process holds it, as a running fit does)."""
    from risp_train.config import make_config
    from risp_train.train import TrainingStopped, fit

    run = tmp_path / "run"
    cfg = make_config(data["train"], str(run), preset="cpu", epochs=2, batch_size=2, width=4, workers=0,
                      shuffle_buffer=4, stats_samples=16, checkpoint_every=3)
    with pytest.raises(TrainingStopped):
        fit(cfg, progress=False, stop_after_step=4)  # a run with a checkpoint to resume from
    before = {n: (run / n).read_bytes() for n in os.listdir(run) if (run / n).is_file()}
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys; from risp_data.atomic import folder_lock\n"
        f"with folder_lock({str(run)!r}, 'busy'):\n"
        "    print('held', flush=True); sys.stdin.read()")],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=ENV)
    try:
        assert holder.stdout.readline().strip() == "held"
        line = _one_line_error(CliRunner().invoke(train_cli, ["fit", data["train"], "--out", str(run), *_TINY,
                                                              "--epochs", "1", "--overwrite"]))
        assert "another risp-train fit is writing to" in line
        with pytest.raises(RispError, match="another risp-train fit is writing to"):
            fit(cfg, progress=False, resume=True)
        assert {n: (run / n).read_bytes() for n in os.listdir(run) if (run / n).is_file()} == before
    finally:
        holder.communicate("")
    fit(cfg, progress=False, resume=True)  # the lock went with its holder; the lock file itself stays
    assert (run / ".lock").is_file() and (run / "model.pt").is_file()


def test_a_fit_decided_on_a_folder_another_fit_changed_meanwhile_stops(data, tmp_path, monkeypatch):
    """B read last.pt (or found none) while A was still training; A finished before B took the lock, and B went
    on — training anew over A's finished model.pt (with other options, which a resume would have refused).  After
    the lock, the folder must still be what the decisions were made on."""
    import risp_train.train as train
    from risp_train.config import make_config

    run = tmp_path / "run"
    cfg = make_config(data["train"], str(run), preset="cpu", epochs=2, batch_size=2, width=4, workers=0,
                      shuffle_buffer=4, stats_samples=16, checkpoint_every=3)
    with pytest.raises(train.TrainingStopped):
        train.fit(cfg, progress=False, stop_after_step=4)
    real = train.check_writable

    def another_fit_finishes(*a, **kw):  # between the decision and the lock
        real(*a, **kw)
        shutil.copy(run / "last.pt", run / "model.pt")
        os.replace(run / "model.pt", run / "last.pt.new")
        os.replace(run / "last.pt.new", run / "last.pt")

    monkeypatch.setattr(train, "check_writable", another_fit_finishes)
    before = (run / "last.pt").read_bytes()
    with pytest.raises(RispError, match="changed while this fit read its data"):
        train.fit(cfg, progress=False, resume=True)
    assert (run / "last.pt").read_bytes() == before
    fresh = tmp_path / "fresh"

    def a_model_appears(*a, **kw):
        real(*a, **kw)
        fresh.mkdir(exist_ok=True)
        (fresh / "model.pt").write_bytes(before)

    monkeypatch.setattr(train, "check_writable", a_model_appears)
    with pytest.raises(RispError, match="changed while this fit read its data"):
        train.fit(make_config(data["train"], str(fresh), preset="cpu", epochs=1, batch_size=2, width=4, workers=0,
                              shuffle_buffer=4, stats_samples=16), progress=False)
    assert (fresh / "model.pt").read_bytes() == before


def test_overwrite_leaves_a_running_writers_temporaries_and_a_shard_folder_is_no_run(data, model, tmp_path):
    """fit --overwrite unlinked every `.tmp*` name itself — also an eval's temporary while it wrote into the run
    folder (the eval then failed, or "wrote" files that were gone); and the `.lock` a render folder holds made
    the folder pass for a run folder, so fit wrote model.pt among the shards."""
    import tempfile

    from risp_data.atomic import temp_prefix

    run = tmp_path / "run"
    r = CliRunner().invoke(train_cli, ["fit", data["train"], "--out", str(run), *_TINY, "--epochs", "1"])
    assert r.exit_code == 0, r.output
    fd, live = tempfile.mkstemp(prefix=temp_prefix(), suffix=".png", dir=run)  # this (live) process's
    os.close(fd)
    (run / ".tmp-killed.png").write_bytes(b"half")
    r = CliRunner().invoke(train_cli, ["fit", data["train"], "--out", str(run), *_TINY, "--epochs", "1",
                                       "--overwrite", "--seed", "2"])
    assert r.exit_code == 0, r.output
    assert os.path.exists(live) and not (run / ".tmp-killed.png").exists()
    shards = tmp_path / "shards"
    shutil.copytree(data["train"], shards)
    (shards / ".lock").touch()
    line = _one_line_error(CliRunner().invoke(train_cli, ["fit", data["train"], "--out", str(shards), *_TINY,
                                                          "--epochs", "1"]))
    assert "holds no risp-train run" in line and not (shards / "model.pt").exists()


def test_a_lock_that_cannot_be_taken_says_why_and_opens_for_the_group(tmp_path, monkeypatch):
    """A file system without flock (NFS mounted nolock) answered "another render is writing" for ever; and the
    .lock was 0644 whatever the umask, so on a group-shared folder only its creator could lock it again."""
    import errno
    import fcntl

    from risp_data.atomic import folder_lock

    old = os.umask(0o002)
    try:
        with folder_lock(tmp_path, "busy"):
            pass
    finally:
        os.umask(old)
    assert (tmp_path / ".lock").stat().st_mode & 0o777 == 0o664

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with pytest.raises(RispError, match=r"cannot lock .*No locks available \(a file system without flock"):
        with folder_lock(tmp_path, "busy"):
            pass


def test_results_name_the_model_bytes_they_used(data, model, tmp_path, monkeypatch):
    """eval (and a task) hashed model.pt when it finished, not when it loaded: a fit --overwrite in between gave
    the old model's numbers the new model's checksum."""
    import risp_train
    import risp_train.evaluate as evaluate
    from risp_data.shards.manifest import sha256_file

    path = tmp_path / "model.pt"
    shutil.copy(model, path)
    loaded = sha256_file(str(path))
    assert risp_train.load(str(path)).sha256 == loaded
    real = evaluate.open_shards

    def replaced_meanwhile(*a, **kw):  # after the load: a fit renames another model into the path
        (tmp_path / "other.pt").write_bytes(path.read_bytes() + b"\0")
        os.replace(tmp_path / "other.pt", path)
        return real(*a, **kw)

    monkeypatch.setattr(evaluate, "open_shards", replaced_meanwhile)
    r = CliRunner().invoke(train_cli, ["eval", str(path), data["train"], "--out", str(tmp_path / "ev"), "--limit", "4"])
    assert r.exit_code == 0, r.output
    assert json.load(open(tmp_path / "ev.json"))["model_sha256"] == loaded != sha256_file(str(path))


def test_replace_folder_writes_through_a_link_the_user_made(tmp_path):
    """--overwrite of a result folder that is a symlink: the folder it points to is replaced and the link kept
    (the link used to be replaced by a real folder, and the old one left as a hidden `.tmp-*` link)."""
    from risp_data.atomic import replace_folder, temp_folder

    real = tmp_path / "disk" / "real"
    real.mkdir(parents=True)
    (real / "old.json").write_text("old")
    (tmp_path / "runs").mkdir()
    link = tmp_path / "runs" / "link"
    os.symlink(real, link)
    tmp = temp_folder(tmp_path / "runs")
    with open(os.path.join(tmp, "new.json"), "w") as f:
        f.write("new")
    replace_folder(tmp, link)
    assert link.is_symlink() and os.path.realpath(link) == str(real)
    assert os.listdir(real) == ["new.json"]
    assert not [n for d in (tmp_path / "runs", tmp_path / "disk") for n in os.listdir(d) if n.startswith(".tmp-")]


# ---------------------------------------------------------------------------- 2. model overwritten


def test_fit_refuses_a_folder_holding_a_model_unless_overwrite(data, model, tmp_path):
    run = tmp_path / "finished"
    run.mkdir()
    shutil.copy(model, run / "model.pt")  # a finished run whose last.pt is gone
    (run / "eval-old.json").write_text('{"model_sha256": "of the old model"}')  # its evaluation
    for mine in ("notes.txt", "evaluate.py", "eval_notes.md"):  # a user's, whatever their names start with
        (run / mine).write_text("mine")
    before = hashlib.sha256((run / "model.pt").read_bytes()).hexdigest()
    runner = CliRunner()
    line = _one_line_error(runner.invoke(train_cli, ["fit", data["train"], "--out", str(run), *_TINY, "--epochs", "1",
                                                     "--seed", "5"]))
    assert "already holds a run (model.pt)" in line and "--overwrite" in line
    line = _one_line_error(runner.invoke(train_cli, ["fit", data["train"], "--out", str(run), *_TINY, "--epochs", "1",
                                                     "--seed", "5", "--resume"]))
    assert "no last.pt to resume from" in line
    assert hashlib.sha256((run / "model.pt").read_bytes()).hexdigest() == before
    r = runner.invoke(train_cli, ["fit", data["train"], "--out", str(run), *_TINY, "--epochs", "1", "--seed", "5",
                                  "--overwrite"])
    assert r.exit_code == 0, r.output
    assert hashlib.sha256((run / "model.pt").read_bytes()).hexdigest() != before
    # the old run's evaluation went with it (it named the replaced model); a user's file stays; nothing kept aside
    assert not (run / "eval-old.json").exists() and not (run / ".overwritten-run").exists()
    assert all((run / mine).read_text() == "mine" for mine in ("notes.txt", "evaluate.py", "eval_notes.md"))


def test_fit_refuses_a_folder_of_other_files_unless_overwrite(data, tmp_path):
    """--out naming a folder that holds files but no run (e.g. someone's notes): one error line, the files
    untouched and nothing written; --overwrite writes the run beside them."""
    folder = tmp_path / "notes"
    folder.mkdir()
    (folder / "a.txt").write_text("mine")
    (folder / "eval.yaml").write_text("mine")  # matched "eval*": --overwrite deleted it
    runner = CliRunner()
    args = ["fit", data["train"], "--out", str(folder), *_TINY, "--epochs", "1", "--seed", "5"]
    line = _one_line_error(runner.invoke(train_cli, args))
    assert "is not empty and holds no risp-train run (a.txt" in line and "--overwrite" in line
    assert sorted(os.listdir(folder)) == ["a.txt", "eval.yaml"]
    r = runner.invoke(train_cli, args + ["--overwrite"])
    assert r.exit_code == 0, r.output
    assert (folder / "model.pt").is_file() and (folder / "a.txt").read_text() == "mine"
    assert (folder / "eval.yaml").read_text() == "mine"


def _sha(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_fit_overwrite_keeps_the_old_run_until_its_first_checkpoint(data, model, tmp_path, monkeypatch):
    """fit --overwrite deleted the old run when training started: a fit that then failed or was stopped before it
    wrote a checkpoint left the folder with no model at all.  The old run now waits in RUN/.overwritten-run and is put
    back when the fit stops early; a SIGKILL (no restore) leaves it there, named by eval and by the next fit, and
    the next fit --overwrite that checkpoints deletes it."""
    from risp_train.config import make_config
    from risp_train.train import TrainingStopped, fit

    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(model, run / "model.pt")
    (run / "eval-old.json").write_text("of the old model")
    old = _sha(run / "model.pt")
    cfg = make_config(data["train"], str(run), preset="cpu", epochs=1, batch_size=4, width=4, workers=0, seed=7)
    notes = []
    with pytest.raises(TrainingStopped):  # stopped at its first step, before any checkpoint
        fit(cfg, progress=False, overwrite=True, stop_after_step=1, echo=notes.append)
    assert _sha(run / "model.pt") == old and (run / "eval-old.json").read_text() == "of the old model"
    assert not (run / ".overwritten-run").exists() and not (run / "losses.csv").exists()  # the stopped fit's log
    assert any("the run it was to replace is back in" in n for n in notes), notes

    from risp_train.train import SetAside

    monkeypatch.setattr(SetAside, "restore", lambda self: None)  # what a SIGKILL leaves: no restore ran
    with pytest.raises(TrainingStopped):
        fit(cfg, progress=False, overwrite=True, stop_after_step=1)
    assert _sha(run / ".overwritten-run" / "model.pt") == old and not (run / "model.pt").exists()
    runner = CliRunner()
    line = _one_line_error(runner.invoke(train_cli, ["eval", str(run), data["train"], "--quiet"]))
    assert ".overwritten-run" in line and "move that folder's files back" in line, line
    args = ["fit", data["train"], "--out", str(run), *_TINY, "--epochs", "1", "--seed", "7"]
    line = _one_line_error(runner.invoke(train_cli, args))
    assert ".overwritten-run holds the run that a fit --overwrite set aside" in line and "--overwrite" in line, line
    assert _sha(run / ".overwritten-run" / "model.pt") == old
    r = runner.invoke(train_cli, args + ["--overwrite"])  # replaces it for good: its checkpoint deletes the old run
    assert r.exit_code == 0, r.output
    assert _sha(run / "model.pt") != old and not (run / ".overwritten-run").exists()
    assert not (run / "eval-old.json").exists()


def test_a_set_aside_run_interrupted_while_deleted_never_replaces_the_new_checkpoint(tmp_path, monkeypatch):
    """The new run's first checkpoint is written, then the replaced run is deleted; Ctrl-C (or an error) during that
    deletion must leave the new checkpoint, not restore a half-deleted old run over it.  And while the new run's
    last.pt is there, eval's error speaks of that unfinished run, not of the set-aside one."""
    import shutil as shutil_module

    from risp_data.errors import RispError
    from risp_train.checkpoint import SET_ASIDE, model_file
    from risp_train.train import SetAside

    run = tmp_path / "run"
    (run / SET_ASIDE).mkdir(parents=True)
    (run / SET_ASIDE / "model.pt").write_bytes(b"old model")
    (run / "last.pt").write_bytes(b"new checkpoint")
    (run / "config.json").write_text("{}")
    aside = SetAside(str(run))

    def interrupted(path, *a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(shutil_module, "rmtree", interrupted)
    with pytest.raises(KeyboardInterrupt):
        with contextlib.ExitStack() as hold:
            hold.push(aside.__exit__)
            aside.drop()
    monkeypatch.undo()
    assert (run / "last.pt").read_bytes() == b"new checkpoint" and (run / "config.json").exists()
    assert not (run / "model.pt").exists() and not aside.pending
    (run / SET_ASIDE).mkdir()  # a fit killed between its checkpoint and the deletion
    (run / SET_ASIDE / "model.pt").write_bytes(b"old model")
    with pytest.raises(RispError, match="has not finished"):
        model_file(str(run))


def _eval_set(prefix):
    """The bytes of the three files an evaluation writes under ``prefix`` (None where absent)."""
    return {s: (open(prefix + s, "rb").read() if os.path.exists(prefix + s) else None)
            for s in (".json", ".md", "_scatter.png")}


def test_eval_refuses_to_replace_earlier_results_unless_overwrite(data, model, tmp_path):
    """eval silently replaced the results an earlier evaluation wrote under its prefix (say another --limit or model):
    now one line naming the existing file and --overwrite; with --overwrite all three files are the new evaluation's."""
    prefix = str(tmp_path / "ev")
    args = ["eval", model, data["train"], "--quiet", "--out", prefix]
    runner = CliRunner()
    r = runner.invoke(train_cli, args + ["--limit", "4"])
    assert r.exit_code == 0, r.output
    first = _eval_set(prefix)
    line = _one_line_error(runner.invoke(train_cli, args + ["--limit", "8"]))
    assert f"{prefix}.json already exists" in line and "--overwrite" in line, line
    assert _eval_set(prefix) == first
    r = runner.invoke(train_cli, args + ["--limit", "8", "--overwrite"])
    assert r.exit_code == 0, r.output
    now = _eval_set(prefix)
    assert all(now[s] != first[s] for s in now)  # every file replaced: n = 8 in the JSON, the table and the plot
    assert json.loads(now[".json"])["n"] == 8 and "n = 8 images" in now[".md"].decode()
    assert sorted(os.listdir(tmp_path)) == ["ev.json", "ev.md", "ev_scatter.png"]  # no temporary left


def test_an_eval_stopped_while_writing_leaves_the_earlier_results_whole(data, model, tmp_path, monkeypatch):
    """eval wrote its JSON, then its table, then its plot, each in place: stopped at the plot (a kill, Ctrl-C, a full
    disk) it left the new JSON and table beside the old plot.  The three are now written into a temporary folder and
    published as a set."""
    import risp_train.plots

    prefix = str(tmp_path / "ev")
    args = ["eval", model, data["train"], "--quiet", "--out", prefix, "--overwrite"]
    r = CliRunner().invoke(train_cli, args + ["--limit", "4"])
    assert r.exit_code == 0, r.output
    first = _eval_set(prefix)

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(risp_train.plots, "plot_predicted_vs_true", interrupted)
    r = CliRunner().invoke(train_cli, args + ["--limit", "8"])
    assert r.exit_code != 0 and "Aborted" in r.output, r.output  # click's answer to Ctrl-C
    assert _eval_set(prefix) == first and sorted(os.listdir(tmp_path)) == ["ev.json", "ev.md", "ev_scatter.png"]


@pytest.mark.parametrize("failing_move", ["new file in", "old file out"])
def test_publish_files_puts_the_old_set_back_when_a_rename_fails(tmp_path, monkeypatch, failing_move):
    """A rename that fails half-way through publishing (a folder in the way, a permission) leaves the old set, not a
    mix, whether it fails while the new files move in or while the old ones move out."""
    from risp_data.atomic import publish_files, temp_folder

    names = ["a.png", "a.md", "a.json"]
    for n in names:
        (tmp_path / n).write_text("old " + n)
    tmp = temp_folder(tmp_path)
    for n in names:
        open(os.path.join(tmp, n), "w").write("new " + n)
    real, calls = os.replace, []

    def failing(src, dst):
        calls.append(dst)
        moving_in = str(src).startswith(tmp) and ".old" not in str(src)
        moving_out = ".old" in str(dst)
        if str(dst).endswith("a.md") and (moving_in if failing_move == "new file in" else moving_out):
            raise OSError(21, "Is a directory", str(dst))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", failing)
    with pytest.raises(OSError):
        publish_files(tmp, tmp_path, names)
    monkeypatch.setattr(os, "replace", real)
    assert {n: (tmp_path / n).read_text() for n in names} == {n: "old " + n for n in names}
    publish_files(tmp, tmp_path, names)
    assert {n: (tmp_path / n).read_text() for n in names} == {n: "new " + n for n in names}


# ------------------------------------------------------------------------- 3. damaged render folder


def test_render_resume_and_verify_repair_re_render_damaged_shards(data, tmp_path):
    ref = data["train"]
    bad = _copy(ref, tmp_path / "damaged")
    os.unlink(os.path.join(bad, "wds", "shard-000001.tar"))  # deleted
    with open(os.path.join(bad, "data.zarr", "psi", "c", "3", "0"), "r+b") as f:  # truncated
        f.truncate(10)
    tar2 = os.path.join(bad, "wds", "shard-000002.tar")  # same size, other bytes: only sha256 sees it
    raw = bytearray(open(tar2, "rb").read())
    raw[700] ^= 0x01
    open(tar2, "wb").write(bytes(raw))
    cmd = [sys.executable, "-m", "risp_data", "render", "--env", "cube", "--n", "16", "--res", str(RES), "--spp", "1",
           "--shard-size", "4", "--workers", "1", "--quiet", "--out", bad]
    r = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "shard 1 is damaged" in r.stderr and "shard 2 is damaged" in r.stderr and "shard 3 is damaged" in r.stderr
    assert "rendered 12 now" in r.stdout, r.stdout
    for sub in ("wds", "data.zarr"):
        for dirpath, _, files in os.walk(os.path.join(ref, sub)):
            for name in files:
                a = os.path.join(dirpath, name)
                b = os.path.join(bad, os.path.relpath(a, ref))
                assert open(a, "rb").read() == open(b, "rb").read(), b
    assert _manifest(bad)["shards"] == _manifest(ref)["shards"]

    # the same damage repaired by verify --repair (no hand-editing of the manifest)
    bad2 = _copy(ref, tmp_path / "damaged2")
    os.unlink(os.path.join(bad2, "wds", "shard-000000.tar"))
    r = CliRunner().invoke(data_cli, ["verify", bad2, "--repair", "--samples", "1"])
    assert "shard 0 is damaged" in r.output, r.output
    assert open(os.path.join(bad2, "wds", "shard-000000.tar"), "rb").read() == \
        open(os.path.join(ref, "wds", "shard-000000.tar"), "rb").read()


def test_verify_repair_of_a_folder_without_jacobians_repairs_it_and_succeeds(data, tmp_path):
    """`inspect` names `verify --repair` for every damaged folder; on a --no-jacobian (target-domain) one it re-rendered
    the shard and then failed with exit 1 (no Jacobians to verify).  It succeeds, saying what it did; plain
    `verify` there is still one line."""
    ref = data["val8"]
    bad = _copy(ref, tmp_path / "val-damaged")
    tar = os.path.join(bad, "wds", "shard-000000.tar")
    with open(tar, "r+b") as f:
        f.truncate(os.path.getsize(tar) // 2)
    r = CliRunner().invoke(data_cli, ["verify", bad, "--repair"])
    assert r.exit_code == 0, r.output
    assert "sample(s) re-rendered" in r.output and "no Jacobians to verify" in r.output
    assert open(tar, "rb").read() == open(os.path.join(ref, "wds", "shard-000000.tar"), "rb").read()
    r = CliRunner().invoke(data_cli, ["verify", bad])
    assert r.exit_code != 0 and "--no-jacobian" in r.output


def test_repair_renders_with_the_folders_variant_and_a_local_pool_this_machine_has(data, tmp_path, monkeypatch):
    """verify --repair re-renders with the job the manifest records: its resolved variant (not the one this machine
    would pick: a CPU folder repaired on a GPU machine), and a local pool of at most this machine's CPUs (the
    folder may have been rendered by a ray cluster or a bigger machine)."""
    import risp_data.generate as generate
    from risp_data import threads
    from risp_data.verify import repair_folder

    folder = _copy(data["train"], tmp_path / "to-repair")
    m = _manifest(folder)
    m["args"].update(variant=None, executor="ray", workers=64)  # as a default-variant ray job records them
    _save_manifest(folder, m)
    jobs = []
    monkeypatch.setattr(generate, "run_job", lambda job, **kw: jobs.append(job) or {})
    monkeypatch.setattr(threads, "available_cpus", lambda: 3)
    repair_folder(folder, progress=False, log=lambda *_: None)
    (job,) = jobs
    assert job.variant == m["variant"] and job.variant is not None
    assert job.executor == "local" and job.workers == 3 and job.out == folder


def test_a_resume_with_other_package_versions_says_so(data, tmp_path):
    """The manifest records the versions a folder was created with; a resume that renders with others says so."""
    folder = _copy(data["train"], tmp_path / "versions")
    m = _manifest(folder)
    m["shards"] = m["shards"][:3]
    m["versions"]["mitsuba"] = "0.0.1"
    save_manifest(folder, m)
    shutil.rmtree(os.path.join(folder, MARKER_DIR))  # shard 3 must be rendered again, not merged from its marker
    r = subprocess.run([sys.executable, "-m", "risp_data", "render", "--env", "cube", "--n", "16", "--res", str(RES),
                        "--spp", "1", "--shard-size", "4", "--workers", "1", "--quiet", "--out", folder],
                       capture_output=True, text=True, env=ENV, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "was rendered with mitsuba 0.0.1 (now " in r.stderr and "rendered 4 now" in r.stdout, (r.stderr, r.stdout)


def test_rendered_now_counts_only_this_call_and_partial_temporaries_are_removed(data, tmp_path):
    folder = _copy(data["train"], tmp_path / "resume")
    m = _manifest(folder)
    m["shards"] = m["shards"][:2]  # shards 2 and 3 finished (markers on disk) but their manifest update was lost
    save_manifest(folder, m)  # with the counts of the two listed shards, as the killed run left it
    stale = os.path.join(folder, "data.zarr", "images", "c", "0", "0", "0", "0.3f2a.partial")  # a killed zarr write
    open(stale, "wb").write(b"half")
    r = subprocess.run([sys.executable, "-m", "risp_data", "render", "--env", "cube", "--n", "16", "--res", str(RES),
                        "--spp", "1", "--shard-size", "4", "--workers", "1", "--quiet", "--out", folder],
                       capture_output=True, text=True, env=ENV, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "16/16 samples in 4/4 shards" in r.stdout and "rendered 0 now" in r.stdout, r.stdout
    assert not os.path.exists(stale)


# ------------------------------------------------------------------------------- 4. incomplete folder


def test_training_on_an_incomplete_folder_needs_allow_incomplete_and_records_the_count(data, tmp_path):
    part = _copy(data["train"], tmp_path / "partial")
    m = _manifest(part)
    m["shards"] = m["shards"][:2]
    m["complete"] = False
    _save_manifest(part, m)
    runner = CliRunner()
    line = _one_line_error(runner.invoke(train_cli, ["fit", part, "--out", str(tmp_path / "r1"), *_TINY]))
    assert "incomplete: 8 of 16 samples" in line and "--allow-incomplete" in line
    assert not (tmp_path / "r1").exists()
    r = runner.invoke(train_cli, ["fit", part, "--out", str(tmp_path / "r2"), *_TINY, "--epochs", "1",
                                  "--allow-incomplete"])
    assert r.exit_code == 0, r.output
    cfg = json.load(open(tmp_path / "r2" / "config.json"))
    assert cfg["samples"]["used"] == 8 and cfg["samples"]["rendered_n"] == 16, cfg["samples"]
    # eval on the unfinished folder works (an evaluation may be meant) but says what it is over
    r = runner.invoke(train_cli, ["eval", str(tmp_path / "r2"), part, "--out", str(tmp_path / "e"), "--quiet",
                                  "--threads", "1"])
    assert r.exit_code == 0 and "is incomplete (8 of 16 samples rendered)" in r.output, r.output
    r = runner.invoke(train_cli, ["eval", str(tmp_path / "r2"), data["train"], "--out", str(tmp_path / "e2"),
                                  "--quiet", "--threads", "1"])
    assert r.exit_code == 0 and "note:" not in r.output, r.output


# ------------------------------------------------------------------ 5. val resolution, spliced shard


def test_fit_refuses_val_shards_of_another_resolution(data, tmp_path):
    line = _one_line_error(CliRunner().invoke(train_cli, ["fit", data["train"], "--out", str(tmp_path / "r"), *_TINY,
                                                          "--val", data["val8"]]))
    assert "8×8" in line and "16×16" in line
    assert not (tmp_path / "r").exists()


def test_a_tar_of_another_environment_spliced_into_a_folder_is_refused(data, tmp_path):
    from risp_data.shards import iter_wds
    from risp_data.shards.manifest import file_record

    bad = _copy(data["train"], tmp_path / "spliced")
    rel = "wds/shard-000001.tar"
    shutil.copy(os.path.join(data["quad"], rel), os.path.join(bad, rel))
    m = _manifest(bad)  # the splicer also updated the manifest's size and hash
    m["shards"][1]["files"][rel] = file_record(bad, rel)
    _save_manifest(bad, m)
    with pytest.raises(RispError, match="holds 'quadrotor' samples"):
        list(iter_wds(bad))
    line = _one_line_error(CliRunner().invoke(train_cli, ["fit", bad, "--out", str(tmp_path / "r"), *_TINY,
                                                          "--format", "wds"]))
    assert "shard-000001.tar holds 'quadrotor' samples" in line and "'cube'" in line


# ------------------------------------------------------------------------- 6. NaN weights, zero std


@pytest.mark.parametrize("damage", ["nan-weight", "zero-std"])
def test_eval_refuses_nan_weights_and_zero_image_std(data, model, tmp_path, damage):
    ck = torch.load(model, weights_only=True)
    if damage == "nan-weight":
        name = next(k for k, v in ck["model"].items() if v.is_floating_point())
        ck["model"][name] = ck["model"][name].clone().fill_(float("nan"))
        expected = "non-finite (NaN/inf) weights"
    else:
        ck["normalization"]["image_std"] = [0.0, 0.1, 0.1]
        expected = "normalization image_std"
    path = tmp_path / f"{damage}.pt"
    torch.save(ck, path)
    line = _one_line_error(CliRunner().invoke(train_cli, ["eval", str(path), data["train"], "--quiet",
                                                          "--out", str(tmp_path / "ev")]))
    assert expected in line and str(path) in line


# --------------------------------------------------------------- 7. loss history of a resumed epoch


def test_resumed_mid_epoch_history_equals_the_uninterrupted_one(data, tmp_path):
    from risp_train.config import make_config
    from risp_train.train import TrainingStopped, fit

    def cfg(out):
        return make_config(data["train"], str(out), preset="cpu", epochs=2, batch_size=2, width=4, workers=0,
                           shuffle_buffer=4, stats_samples=16, checkpoint_every=3)

    fit(cfg(tmp_path / "ref"), progress=False)
    with pytest.raises(TrainingStopped):
        fit(cfg(tmp_path / "cut"), progress=False, stop_after_step=4)  # checkpoint at step 3, mid-epoch 0
    fit(cfg(tmp_path / "cut"), progress=False, resume=True)
    ref = json.load(open(tmp_path / "ref" / "history.json"))
    cut = json.load(open(tmp_path / "cut" / "history.json"))
    assert len(ref) == len(cut) == 2
    for a, b in zip(ref, cut):
        for k in ("train_loss", "train_error", "train_reg"):
            assert a[k] == pytest.approx(b[k], rel=1e-6, abs=1e-9), (k, a, b)


# --------------------------------------------------------------------- 8. plain zarr readers


@pytest.mark.parametrize("fail_after", [1, 2, 3])
def test_plain_zarr_reader_never_sees_a_partly_written_sample(tmp_path, monkeypatch, fail_after):
    """A writer killed between a shard's arrays: for every sample a plain zarr reader sees either a NaN state
    row (unwritten) or every array finite, and the store's ``complete_shards`` attribute excludes the shard."""
    import zarr

    from risp_data.shards.manifest import save_manifest
    from risp_data.shards.writer import write_shard
    from risp_data.shards.zarr_store import create_store, mark_complete_shards
    from tests.test_shards import _manifest as fmt_manifest
    from tests.test_shards import _sample

    folder = str(tmp_path)
    m = fmt_manifest(4, 2, formats=("zarr",))
    save_manifest(folder, m)
    create_store(folder, m)
    rng = np.random.default_rng(0)
    samples = [_sample(i, rng) for i in range(4)]
    m["shards"].append(write_shard(folder, ("zarr",), 0, samples[:2]))
    save_manifest(folder, m)
    mark_complete_shards(folder, m)

    calls = {"n": 0}
    original = zarr.Array.__setitem__

    def killed_after(self, key, value):
        if calls["n"] == fail_after:
            raise KeyboardInterrupt("killed between arrays")
        calls["n"] += 1
        return original(self, key, value)

    monkeypatch.setattr(zarr.Array, "__setitem__", killed_after)
    with pytest.raises(KeyboardInterrupt):
        write_shard(folder, ("zarr",), 1, samples[2:])
    monkeypatch.undo()

    root = zarr.open_group(os.path.join(folder, "data.zarr"), mode="r")
    assert list(root.attrs["complete_shards"]) == [0]
    arrays = {name: np.asarray(root[name][:]) for name in ("images", "jacobians", "states", "psi")}
    for i in range(4):
        if np.isfinite(arrays["states"][i]).all():
            for name, a in arrays.items():
                assert np.isfinite(a[i]).all(), (i, name)


# ------------------------------------------------------------------ tracebacks → one Error: line


def test_os_errors_are_one_error_line_naming_the_file(data, model, tmp_path):
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    runner = CliRunner()
    line = _one_line_error(runner.invoke(train_cli, ["fit", data["train"], "--out", str(a_file / "run"), *_TINY]))
    assert str(a_file) in line
    line = _one_line_error(runner.invoke(train_cli, ["eval", model, data["train"], "--quiet", "--out",
                                                     str(a_file / "sub" / "ev")]))
    assert str(a_file) in line
    proc = subprocess.run([sys.executable, "-m", "cli", "demo", "--quick", "--out", str(a_file / "demo")],
                          capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=600)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1].startswith("Error:") and str(a_file) in proc.stderr


@pytest.mark.parametrize("value", ["nan", "-1", "inf"])
def test_bad_weight_decay_is_refused_before_the_run_folder_exists(data, tmp_path, value):
    out = tmp_path / "run"
    line = _one_line_error(CliRunner().invoke(train_cli, ["fit", data["train"], "--out", str(out), *_TINY,
                                                          "--weight-decay", value]))
    assert "--weight-decay must be a finite number >= 0" in line
    assert not out.exists()


def test_res_beyond_mitsuba_or_memory_is_refused_and_leaves_the_folder_usable(tmp_path):
    out = tmp_path / "big"
    base = ["render", "--env", "cube", "--n", "2", "--spp", "1", "--workers", "1", "--quiet", "--out", str(out)]
    runner = CliRunner()
    line = _one_line_error(runner.invoke(data_cli, [*base, "--res", "100000"]))
    assert "--res 100000" in line
    line = _one_line_error(runner.invoke(data_cli, [*base, "--res", "8192", "--spp", "64"]))
    assert "--res 8192 with --spp 64" in line and "2^32" in line
    line = _one_line_error(runner.invoke(data_cli, [*base, "--res", "0"]))
    assert line == "Error: --res must be a positive integer, got 0"
    r = runner.invoke(data_cli, [*base, "--res", "8"])  # the corrected command works in the same folder
    assert r.exit_code == 0, r.output


def test_a_failed_first_shard_does_not_block_the_folder(tmp_path, monkeypatch):
    """A job that wrote its manifest but no shard (e.g. the renderer refused the image size) must not
    block a corrected command with 'holds another job'."""
    from risp_data.generate import RenderJob, new_manifest
    from risp_data.shards.manifest import save_manifest

    out = tmp_path / "f"
    out.mkdir()
    save_manifest(str(out), new_manifest(RenderJob(env="cube", n=2, out=str(out), resolution=4096, spp=1,
                                                   formats=("wds",)), "llvm_ad_rgb"))
    r = CliRunner().invoke(data_cli, ["render", "--env", "cube", "--n", "2", "--res", "8", "--spp", "1",
                                      "--workers", "1", "--quiet", "--format", "wds", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert _manifest(str(out))["resolution"] == 8


def test_memory_estimate_refuses_a_job_larger_than_the_machine(tmp_path):
    from risp_data.generate import RenderJob, available_memory, memory_estimate

    job = RenderJob(env="cube", n=512, out="unused", resolution=8000, spp=1, workers=2)
    need = memory_estimate(job, 8)
    assert need > 2 * 256 * 9 * 8000 * 8000 * 12  # two workers each holding a shard of images + Jacobians
    have = available_memory()
    assert have is not None and 0 < have < need
    out = tmp_path / "huge"
    line = _one_line_error(CliRunner().invoke(data_cli, ["render", "--env", "cube", "--n", "512", "--res", "8000",
                                                         "--spp", "1", "--workers", "2", "--quiet", "--out", str(out)]))
    assert "--res 8000 needs about" in line and "GiB of memory" in line
    assert not out.exists()


def test_corrupt_and_empty_checkpoints_are_one_line_without_torchs_advice(data, tmp_path):
    import argparse

    pickled = tmp_path / "pickled.pt"
    torch.save({"format": "risp-train-checkpoint", "x": argparse.Namespace(a=1)}, pickled)
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    runner = CliRunner()
    line = _one_line_error(runner.invoke(train_cli, ["eval", str(pickled), data["train"], "--quiet"]))
    assert "weights_only" not in line and "pickled argparse.Namespace object" in line and str(pickled) in line
    line = _one_line_error(runner.invoke(train_cli, ["eval", str(empty), data["train"], "--quiet"]))
    assert "is empty (0 bytes)" in line and str(empty) in line


def _set(path, value):
    """A checkpoint edit: the entry at ``path`` (keys from the top) set to ``value``."""
    def edit(ck):
        *parents, last = path
        for key in parents:
            ck = ck[key]
        ck[last] = value(ck[last]) if callable(value) else value
    return edit


@pytest.mark.parametrize("edit, expected", [
    (_set(("normalization", "target_mean"), lambda v: v[:-2]),
     "normalization target_mean has 7 entries, the checkpoint has 9 target_names"),
    (_set(("normalization", "image_std"), [1.0, 1.0]), "normalization image_std has 2 entries, the checkpoint has 3 colour"),
    (_set(("target_names",), lambda v: v[:6]), "normalization target_mean has 9 entries, the checkpoint has 6 target_names"),
    (_set(("model_config", "out_dim"), 6), "the network predicts 6 targets, the checkpoint has 9 target_names"),
    (_set(("resolution",), 8), "resolution 8 does not suit its network (stem 'small' takes images of at least 9×9)"),
    (_set(("model_config", "stem"), "imagenet"), "resolution 16 does not suit its network (stem 'imagenet'"),
])
def test_an_inconsistent_checkpoint_is_one_line_naming_it(data, model, tmp_path, edit, expected):
    """A checkpoint whose parts disagree (edited by hand, or pieced from two runs) loaded and then failed at its first
    use with a traceback ("The size of tensor a (9) must match ...", "input (8, 8) is too small for stem"): now
    eval, risp_train.load and the tasks' load_checkpoint refuse it when reading, naming the file."""
    import risp_train
    from risp_train.checkpoint import load_checkpoint

    ck = torch.load(model, weights_only=True)
    edit(ck)
    bad = tmp_path / "edited.pt"
    torch.save(ck, bad)
    line = _one_line_error(CliRunner().invoke(train_cli, ["eval", str(bad), data["train"], "--quiet",
                                                          "--out", str(tmp_path / "ev")]))
    assert f"inconsistent checkpoint {bad}: {expected}" in line, line
    assert not (tmp_path / "ev.json").exists()
    for read in (risp_train.load, load_checkpoint):
        with pytest.raises(RispError, match="inconsistent checkpoint"):
            read(str(bad))


def test_a_text_or_other_file_given_as_the_model_is_named_for_what_it_is(data, model, tmp_path):
    """An eval's own .md (or .json) passed as MODEL gave "corrupt or unreadable checkpoint ...: KeyError: 101" (the
    text's first byte read as a pickle opcode); its plot "UnpicklingError: Unsupported operand 80"; a .npz "file in
    archive is not in a subdirectory".  Each is now one line saying what the file is."""
    import numpy as np

    runner = CliRunner()
    r = runner.invoke(train_cli, ["eval", model, data["train"], "--quiet", "--limit", "4", "--out", str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output
    np.savez(tmp_path / "arrays.npz", a=np.zeros(3))
    for name, expected in (("ev.md", "is a text file (it begins 'State estimation on "),
                           ("ev.json", "is a text file (it begins '{'), not a risp-train checkpoint"),
                           ("ev_scatter.png", "a PNG image, not a risp-train checkpoint"),
                           ("arrays.npz", "a zip archive of a.npy without torch's data.pkl")):
        path = str(tmp_path / name)
        line = _one_line_error(runner.invoke(train_cli, ["eval", path, data["train"], "--quiet",
                                                         "--out", str(tmp_path / "again")]))
        assert path in line and expected in line, line


_DISK_FULL_RENDER = r"""
import errno, sys
import zarr.storage._local as local
real = local._put
def full(path, value, exclusive=False):
    if "/c/" in str(path):  # what a full disk raises from write(): no file name
        raise OSError(errno.ENOSPC, "No space left on device")
    return real(path, value, exclusive)
local._put = full
from risp_data.cli import main
sys.argv = ["risp-data"] + sys.argv[1:]
main()
"""

_DISK_FULL_CHECKPOINT = r"""
import errno, io, os, sys
import risp_data.atomic as atomic
real_fdopen = os.fdopen
class Full:
    # a binary file on a disk with 2000 bytes left: write() fails like a full disk (ENOSPC, no file name)
    def __init__(self, f):
        self.f, self.n = f, 0
    def write(self, b):
        self.n += len(b)
        if self.n > 2000:
            raise OSError(errno.ENOSPC, "No space left on device")
        return self.f.write(b)
    def __getattr__(self, name):
        return getattr(self.f, name)
    def __enter__(self):
        return self
    def __exit__(self, *exc):
        return self.f.__exit__(*exc)
def fdopen(fd, mode="r", *a, **k):
    f = real_fdopen(fd, mode, *a, **k)
    return Full(f) if "b" in mode and "w" in mode else f
atomic.os = type(sys)("os_full")  # only risp's atomic writer sees the full disk
atomic.os.__dict__.update(os.__dict__)
atomic.os.fdopen = fdopen
from risp_train.cli import main
sys.argv = ["risp-train"] + sys.argv[1:]
main()
"""


def test_disk_full_during_render_and_checkpoint_write_is_one_line(data, tmp_path):
    out = tmp_path / "full"
    r = subprocess.run([sys.executable, "-c", _DISK_FULL_RENDER, "render", "--env", "cube", "--n", "4", "--res", "8",
                        "--spp", "1", "--shard-size", "2", "--workers", "1", "--quiet", "--out", str(out)],
                       capture_output=True, text=True, env=ENV, timeout=600)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("Error:") and "No space left on device" in last and "data.zarr" in last, last
    assert _manifest(str(out))["shards"] == []  # nothing claimed complete
    run = tmp_path / "run"
    r = subprocess.run([sys.executable, "-c", _DISK_FULL_CHECKPOINT, "fit", data["train"], "--out", str(run), *_TINY,
                        "--epochs", "1"], capture_output=True, text=True, env=ENV, timeout=600)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("Error:") and "No space left on device" in last and "last.pt" in last, last
    assert not [n for n in os.listdir(run) if n.startswith(".tmp-")]  # no half-written temporary left


def _children(pid):
    """The children of every thread of ``pid`` (threads start and end while this reads: a vanished one is skipped)."""
    out = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:  # the process itself is gone
        return out
    for task in tasks:
        try:
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(c) for c in f.read().split()]
        except OSError:
            continue
    return out


def _kill_a_child_when_running(proc, wait_for, timeout=300, settle=0.3, children=_children):
    import signal
    import time

    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        kids = [c for c in children(proc.pid) if wait_for(c)]
        if kids:
            time.sleep(settle)  # let it start working
            try:
                os.kill(kids[0], signal.SIGKILL)
                return True
            except ProcessLookupError:
                continue  # it had finished: wait for the next one
        time.sleep(0.05)
    return False


def _cmdline(pid):
    try:
        return open(f"/proc/{pid}/cmdline", "rb").read().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def _pool_workers(pid):
    """The render pool's worker processes: forks of the job's fork server (risp_data.generate.worker_context),
    or the job's own multiprocessing children where it spawns them; never the fork server or resource tracker."""
    out = []
    for c in _children(pid):
        cmd = _cmdline(c)
        if "forkserver" in cmd:
            out += _children(c)
        elif "multiprocessing" in cmd and "resource_tracker" not in cmd:
            out.append(c)
    return out


def test_a_killed_render_worker_is_one_line_and_the_job_resumes(tmp_path):
    out = tmp_path / "pool"
    cmd = [sys.executable, "-m", "risp_data", "render", "--env", "cube", "--n", "24", "--res", "16", "--spp", "1",
           "--shard-size", "2", "--workers", "2", "--quiet", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    killed = _kill_a_child_when_running(proc, lambda c: True, children=_pool_workers)
    _, err = proc.communicate(timeout=600)
    assert killed, "no pool worker to kill"
    assert proc.returncode == 1 and "Traceback" not in err, err[-3000:]
    assert err.strip().splitlines()[-1].startswith("Error: a worker process died unexpectedly"), err[-1000:]
    r = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=600)
    assert r.returncode == 0 and "24/24 samples" in r.stdout, r.stderr


def test_a_killed_dataloader_worker_is_one_line(data, tmp_path):
    cmd = [sys.executable, "-m", "risp_train", "fit", data["train"], "--out", str(tmp_path / "run"), "--preset", "cpu",
           "--width", "4", "--batch-size", "1", "--workers", "1", "--epochs", "50", "--format", "zarr", "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    killed = 0
    for _ in range(5):  # a worker killed after its last batch of an epoch goes unnoticed: kill the next one
        # settle=0: with one torch thread a tiny epoch (and its worker's life) lasts well under 0.3 s
        killed += _kill_a_child_when_running(proc, lambda c: not any(w in _cmdline(c) for w in ("forkserver",
                                                                                               "resource_tracker")),
                                             settle=0.0)
        try:
            proc.wait(timeout=10)
            break
        except subprocess.TimeoutExpired:
            continue
    if proc.poll() is None:
        proc.kill()
    _, err = proc.communicate(timeout=600)
    assert killed, "no DataLoader worker to kill: " + err[-2000:]
    assert proc.returncode == 1 and "Traceback" not in err, err[-3000:]
    assert err.strip().splitlines()[-1].startswith("Error: a data-loading worker process died"), err[-1000:]


def _alive(pid):
    """Running (a zombie, ended but not yet collected, is not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except OSError:
        return False


def test_render_workers_end_when_the_job_process_is_killed(tmp_path):
    """SIGKILL on a `--workers 2` render (no pool shutdown): its workers, forks of the fork server and not the
    job's children, stop instead of writing on into a folder whose lock is gone (a rerun would take it)."""
    import signal
    import time

    out = tmp_path / "orphans"
    cmd = [sys.executable, "-m", "risp_data", "render", "--env", "cube", "--n", "400", "--res", "16", "--spp", "1",
           "--shard-size", "2", "--workers", "2", "--quiet", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV)
    workers = []
    try:
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None:
            workers = _pool_workers(proc.pid)
            if len(workers) >= 2 and os.path.isdir(out / MARKER_DIR) and os.listdir(out / MARKER_DIR):
                break  # both workers are rendering shards
            time.sleep(0.2)
        assert len(workers) >= 2, "the render did not start two pool workers"
        proc.kill()
        proc.wait()
        deadline = time.time() + 20
        while any(_alive(w) for w in workers) and time.time() < deadline:
            time.sleep(0.2)
        assert not [w for w in workers if _alive(w)], "render workers went on after their job was killed"
    finally:
        if proc.poll() is None:
            proc.kill()
        for w in workers:
            if _alive(w):
                os.kill(w, signal.SIGKILL)


def test_a_pid_given_to_another_process_counts_as_gone():
    """exit_with's test: the job's pid with another start time (the pid reused after the job ended) is gone."""
    from risp_data.processes import process_gone, start_time

    me = os.getpid()
    started = start_time(me)
    assert started is not None and not process_gone(me, started) and not process_gone(me)
    assert process_gone(me, str(int(started) + 1))
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    assert process_gone(child.pid)


def test_a_helper_whose_parent_is_already_gone_ends():
    """A DataLoader worker (risp_train.data._WorkerInit) or render worker that starts after its parent died ends at
    once instead of waiting on its queue forever: exit_with on a gone process exits within its period."""
    import time

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    code = ("import time, sys; from risp_data.processes import exit_with; "
            f"exit_with({gone.pid}, period=0.1); time.sleep(60); sys.exit(0)")
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", code], env=ENV, timeout=50)
    assert r.returncode == 1 and time.monotonic() - t0 < 30
    from risp_train.data import _WorkerInit

    init = _WorkerInit()  # made in the process that makes the DataLoader: names it by pid and start time
    assert init.parent == os.getpid() and init.started is not None


def test_atomic_write_over_a_folder_names_the_file_not_the_temporary(tmp_path):
    """The final rename fails where a folder stands in the file's place: the error names the file (it named
    `.tmp-… -> file`), and no temporary is left."""
    from risp_data.atomic import atomic_write

    (tmp_path / "e.json").mkdir()
    with pytest.raises(OSError) as e:
        with atomic_write(tmp_path / "e.json", "w") as f:
            f.write("{}")
    assert e.value.filename == str(tmp_path / "e.json") and ".tmp-" not in str(e.value)
    assert os.listdir(tmp_path) == ["e.json"]
