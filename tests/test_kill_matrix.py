"""Kill matrix (issue 13): ``risp-data render`` and ``risp-train fit`` SIGKILLed at chosen moments — inside a
shard write, between zarr arrays, inside a zarr file write, between marker and manifest, inside a manifest or
checkpoint write, between optimizer steps — then resumed with the user's command.

After each kill no reader sees a partial sample (our readers; plain webdataset over every tar on disk; plain
zarr: a sample with a finite ``states`` row has every array finite) and no reader sees a partial checkpoint;
after the resume the outputs equal an uninterrupted run's (shard files byte for byte; weights bitwise at one
thread with in-process data loading, the condition under which training is deterministic here).

CI-size: 8 samples of 16×16 pixels at 1 spp, a width-4 network; each case runs two short processes.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=ROOT)

# The driver installs one kill point (KILL_POINT, KILL_AT = the call that dies) and runs the CLI.  A kill is a
# real SIGKILL of the process: no cleanup handler runs, exactly as with `kill -9` or the OOM killer.
_DRIVER = r"""
import io, os, signal, sys
point, at = os.environ["KILL_POINT"], int(os.environ["KILL_AT"])
calls = {"n": 0}
def due():
    calls["n"] += 1
    return calls["n"] == at
def die():
    os.kill(os.getpid(), signal.SIGKILL)

def wrap(owner, name, before=None):
    real = getattr(owner, name)
    def patched(*a, **k):
        if due():
            (before or (lambda *a, **k: None))(*a, **k)
            die()
        return real(*a, **k)
    setattr(owner, name, patched)

if point == "tar-member":  # inside a tar shard's write: some members in its temporary file
    import tarfile
    wrap(tarfile.TarFile, "addfile")
elif point == "zarr-between-arrays":
    import zarr
    wrap(zarr.Array, "__setitem__")
elif point == "zarr-file-write":  # inside zarr's own write: half a shard file in its .partial temporary
    import zarr.storage._local as local
    def half(path, value, exclusive=False):
        tmp = path.with_suffix(".killed.partial")
        tmp.parent.mkdir(parents=True, exist_ok=True)
        data = bytes(value.as_buffer_like())
        tmp.write_bytes(data[: len(data) // 2])
    real_put = local._put
    def put(path, value, exclusive=False):
        if "/c/" in str(path) and due():
            half(path, value)
            die()
        return real_put(path, value, exclusive)
    local._put = put
elif point == "before-manifest-update":  # shard files and marker written, manifest not updated
    import risp_data.generate as g
    wrap(g, "save_manifest")
elif point == "manifest-write":  # the manifest's temporary written, not yet renamed
    real_replace = os.replace
    def replace(src, dst, *a, **k):
        if str(dst).endswith("manifest.json") and due():
            die()
        return real_replace(src, dst, *a, **k)
    os.replace = replace
elif point == "mid-shard":  # between two samples of a shard
    import risp_data.generate as g
    wrap(g, "render_sample")
elif point == "optimizer-step":
    import torch
    wrap(torch.optim.Adam, "step")
elif point == "checkpoint-write":  # half a checkpoint in its temporary file
    import torch
    real_save = torch.save
    def save(obj, f, *a, **k):
        if due() and hasattr(f, "write"):
            buf = io.BytesIO()
            real_save(obj, buf, *a, **k)
            f.write(buf.getvalue()[: len(buf.getvalue()) // 2])
            f.flush()
            die()
        return real_save(obj, f, *a, **k)
    torch.save = save
elif point == "after-checkpoint":  # last.pt renamed into place, plot and history not yet written
    import risp_train.plots as plots
    wrap(plots, "plot_losses")
else:
    raise SystemExit(f"unknown kill point {point}")

tool = sys.argv[1]
sys.argv = [tool] + sys.argv[2:]
if tool == "risp-data":
    from risp_data.cli import main
else:
    from risp_train.cli import main
main()
"""

RENDER = ["--env", "cube", "--n", "8", "--res", "16", "--spp", "1", "--shard-size", "2", "--workers", "1", "--quiet"]
FIT = ["--preset", "cpu", "--epochs", "2", "--batch-size", "2", "--width", "4", "--workers", "0",
       "--checkpoint-every", "3", "--quiet"]


def _run(args, kill=None, timeout=600):
    env = dict(ENV)
    cmd = [sys.executable, "-m", args[0].replace("-", "_")] + args[1:]
    if kill is not None:
        env.update(KILL_POINT=kill[0], KILL_AT=str(kill[1]))
        cmd = [sys.executable, "-c", _DRIVER, *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted render and an uninterrupted training run on it."""
    root = tmp_path_factory.mktemp("kill-reference")
    shards = str(root / "shards")
    r = _run(["risp-data", "render", *RENDER, "--out", shards])
    assert r.returncode == 0, r.stderr
    run = str(root / "run")
    r = _run(["risp-train", "fit", shards, *FIT, "--out", run])
    assert r.returncode == 0, r.stderr
    return {"shards": shards, "run": run}


def _files(folder):
    out = {}
    for sub in ("wds", "data.zarr"):
        for path in glob.glob(os.path.join(folder, sub, "**", "*"), recursive=True):
            if os.path.isfile(path):
                out[os.path.relpath(path, folder)] = open(path, "rb").read()
    return out


def _assert_no_partial_sample(folder):
    """What every kind of reader sees in a folder right after a kill."""
    import webdataset as wds
    import zarr

    from risp_data.shards import ZarrDataset, iter_wds, load_manifest

    if not os.path.exists(os.path.join(folder, "manifest.json")):
        return
    m = load_manifest(folder)
    listed = sum(r["stop"] - r["start"] for r in m["shards"])
    assert len(list(iter_wds(folder))) == listed  # our readers: the listed shards, whole
    ds = ZarrDataset(folder)
    for i in range(len(ds)):
        s = ds[i]
        assert all(np.isfinite(s[k]).all() for k in ("image", "jacobian", "state", "psi")), i
    tars = sorted(glob.glob(os.path.join(folder, "wds", "shard-*.tar")))  # a plain reader of every tar on disk
    for sample in wds.WebDataset(tars, shardshuffle=False, empty_check=False) if tars else []:
        assert {"image.exr", "jacobian.exr", "json", "psi.npy", "state.npy"} <= set(sample), sample["__key__"]
    store = os.path.join(folder, "data.zarr")
    if os.path.exists(os.path.join(store, "states", "zarr.json")):  # a plain zarr reader
        root = zarr.open_group(store, mode="r")
        arrays = {k: np.asarray(root[k][:]) for k in root.array_keys()}  # either Jacobian layout
        for i in range(arrays["states"].shape[0]):
            if np.isfinite(arrays["states"][i]).all():
                assert all(np.isfinite(a[i]).all() for a in arrays.values()), i
        done = set(root.attrs.get("complete_shards", []))
        assert done <= {r["index"] for r in m["shards"]}


RENDER_KILLS = [
    ("mid-shard", 4),  # second shard, after its first sample
    ("tar-member", 15),  # inside shard 1's tar (10 members per shard)
    ("zarr-between-arrays", 8),  # shard 1: its jacobian_planes and _rest written, images, psi and states not
    ("zarr-file-write", 4),  # shard 0's psi file half written (after jacobian_planes, jacobian_rest, images)
    ("before-manifest-update", 3),  # shard 1 complete on disk, not in the manifest
    ("manifest-write", 4),  # the manifest update of shard 2 killed inside its atomic write
]


@pytest.mark.parametrize("point,at", RENDER_KILLS, ids=[p for p, _ in RENDER_KILLS])
def test_render_killed_then_resumed_equals_an_uninterrupted_render(reference, tmp_path, point, at):
    out = str(tmp_path / "shards")
    r = _run(["risp-data", "render", *RENDER, "--out", out], kill=(point, at))
    assert r.returncode == -signal.SIGKILL, (point, r.returncode, r.stderr[-2000:])
    _assert_no_partial_sample(out)
    r = _run(["risp-data", "render", *RENDER, "--out", out])
    assert r.returncode == 0, r.stderr
    assert "8/8 samples" in r.stdout
    want, got = _files(reference["shards"]), _files(out)
    assert sorted(got) == sorted(want), point  # no temporary (.tmp-*, *.partial) left behind
    for rel in want:
        assert got[rel] == want[rel], (point, rel)
    m_ref = json.load(open(os.path.join(reference["shards"], "manifest.json")))
    m_out = json.load(open(os.path.join(out, "manifest.json")))
    assert m_out["shards"] == m_ref["shards"] and m_out["complete"]


# 8 samples, batch 2: 4 steps per epoch, 8 in all; checkpoints (torch.save calls) at steps 3 and 4 (epoch 0 end),
# 6 and 8 (epoch 1 end), then model.pt.
FIT_KILLS = [
    ("optimizer-step", 2),  # before any checkpoint: the resume starts over
    ("optimizer-step", 7),  # mid epoch 1, one step after a mid-epoch checkpoint
    ("checkpoint-write", 2),  # inside the epoch-end checkpoint's write
    ("checkpoint-write", 3),  # inside a mid-epoch checkpoint's write
    ("checkpoint-write", 5),  # inside model.pt's write
    ("after-checkpoint", 1),  # last.pt in place, losses plot and history not yet written
]


@pytest.mark.parametrize("point,at", FIT_KILLS, ids=[f"{p}-{a}" for p, a in FIT_KILLS])
def test_fit_killed_then_resumed_equals_an_uninterrupted_run(reference, tmp_path, point, at):
    from risp_train.checkpoint import load_checkpoint

    run = str(tmp_path / "run")
    r = _run(["risp-train", "fit", reference["shards"], *FIT, "--out", run], kill=(point, at))
    assert r.returncode == -signal.SIGKILL, (point, r.returncode, r.stderr[-2000:])
    for name in ("last.pt", "model.pt"):  # a checkpoint on disk is always a whole one
        if os.path.exists(os.path.join(run, name)):
            load_checkpoint(os.path.join(run, name))
    assert not os.path.exists(os.path.join(run, "model.pt"))
    r = _run(["risp-train", "fit", reference["shards"], *FIT, "--out", run, "--resume"])
    assert r.returncode == 0, r.stderr[-2000:]
    assert not [n for n in os.listdir(run) if n.startswith(".tmp-")]
    want = torch.load(os.path.join(reference["run"], "model.pt"), weights_only=True)
    got = torch.load(os.path.join(run, "model.pt"), weights_only=True)
    for k in want["model"]:
        torch.testing.assert_close(got["model"][k], want["model"][k], rtol=0, atol=0, msg=k)
    hist_ref = json.load(open(os.path.join(reference["run"], "history.json")))
    hist = json.load(open(os.path.join(run, "history.json")))
    assert [h["step"] for h in hist] == [h["step"] for h in hist_ref]
    for a, b in zip(hist, hist_ref):
        assert a["train_loss"] == pytest.approx(b["train_loss"], rel=1e-6), (point, a, b)
    shutil.rmtree(run)
