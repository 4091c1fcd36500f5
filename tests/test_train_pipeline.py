"""risp-train end to end on tiny real shards: fit, resume, eval, load, errors, torchrun.

The shards are rendered once per module by the public ``risp-data render`` command (16×16 pixels,
2 spp, cube): a training set with Jacobians (4 shards) and a held-out set without (other seed).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from risp_data.errors import RispError
from risp_train.cli import cli
from risp_train.config import make_config
from risp_train.train import TrainingStopped, fit

RES = 16


def _render(out, n, shard_size, seed, extra=()):
    cmd = [sys.executable, "-m", "risp_data", "render", "--env", "cube", "--n", str(n), "--res", str(RES),
           "--spp", "2", "--shard-size", str(shard_size), "--seed", str(seed), "--workers", "1", "--quiet",
           "--out", str(out), *extra]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return str(out)


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    root = tmp_path_factory.mktemp("train-shards")
    train = _render(root / "train", 64, 16, 0)
    held_out = _render(root / "held_out", 32, 16, 11, ("--format", "wds", "--no-jacobian"))
    return {"train": train, "held_out": held_out, "root": root}


def _cfg(shards, out, **kw):
    base = dict(preset="cpu", epochs=2, batch_size=4, width=4, workers=0, lr=3e-3, shuffle_buffer=8, stats_samples=32)
    base.update(kw)
    preset = base.pop("preset")
    return make_config(shards["train"], str(out), preset=preset, **base)


def test_fit_lowers_held_out_error_and_writes_outputs(shards, tmp_path):
    out = tmp_path / "run"
    cfg = _cfg(shards, out, epochs=6, batch_size=8, width=8, workers=2, val=shards["held_out"], val_samples=32)
    path = fit(cfg, progress=False)
    hist = json.load(open(out / "history.json"))
    assert hist[0]["epoch"] == -1 and len(hist) == 7
    first, last = hist[0]["val_error"], hist[-1]["val_error"]
    assert last < first - 0.03, (first, last)
    assert hist[-1]["train_error"] < hist[1]["train_error"]
    for name in ("model.pt", "last.pt", "losses.csv", "losses.png", "config.json"):
        assert (out / name).exists(), name
    rows = open(out / "losses.csv").read().strip().splitlines()
    assert len(rows) == 1 + sum(json.load(open(out / "config.json"))["steps_per_epoch"])
    # the checkpoint is plain data: weights_only loading works, and it records what the issue asks for
    ck = torch.load(path, map_location="cpu", weights_only=True)
    for key in ("config", "state_names", "target_names", "normalization", "manifest_hash", "seed", "env", "model"):
        assert key in ck
    assert ck["env"] == "cube" and ck["config"]["reg"] == "none"

    import risp_train

    predictor = risp_train.load(path)
    assert not predictor.training and not any(p.requires_grad for p in predictor.parameters())
    images = torch.rand(3, RES, RES, 3)
    states, targets = predictor.predict(images)
    assert states.shape == (3, 6) and targets.shape == (3, 9)
    torch.testing.assert_close(predictor(images), states)
    with pytest.raises(RispError, match="shape"):
        predictor(torch.rand(3, RES + 1, RES, 3))

    # eval: model, average and random baselines; JSON + markdown
    r = CliRunner().invoke(cli, ["eval", path, shards["held_out"], "--quiet", "--out", str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output
    assert "training error" not in r.output  # held-out images: no note
    r = CliRunner().invoke(cli, ["eval", path, shards["train"], "--quiet", "--limit", "4", "--out", str(tmp_path / "tr")])
    assert r.exit_code == 0 and "is the data the model was trained on: these figures are training error" in r.output
    r = CliRunner().invoke(cli, ["eval", path, shards["held_out"], "--quiet", "--limit", "4", "--out", str(tmp_path / "evdir") + "/"])
    name = "eval-" + os.path.basename(os.path.normpath(shards["held_out"]))
    assert r.exit_code == 0 and sorted(os.listdir(tmp_path / "evdir")) == sorted(
        f"{name}{ext}" for ext in (".json", ".md", "_scatter.png")), os.listdir(tmp_path / "evdir")
    res = json.load(open(tmp_path / "ev.json"))
    assert set(res["results"]) == {"model", "average", "random"} and res["n"] == 32
    for v in res["results"].values():
        assert v["mean"] > 0 and v["std"] > 0 and len(v["per_dim_mae"]) == 6
    md = open(tmp_path / "ev.md").read()
    assert "| model |" in md and f"`random` drawn with seed {res['seed']}" in md  # the table names its seed
    for method in ("model", "average", "random"):  # per state group, physical units (issue 8)
        g = res["groups"][method]
        assert set(g) == {"position", "attitude"} and g["position"]["n"] == 32 and g["attitude"]["unit"] == "deg"
        assert 0 < g["position"]["mean"] < 2 and 0 < g["attitude"]["mean"] <= 180
    assert os.path.getsize(tmp_path / "ev_scatter.png") > 1000
    assert res["results"]["model"]["mean"] < res["results"]["random"]["mean"]
    # the `average` baseline, by hand: the training targets' mean (x, y, z and the cube's rotation columns
    # r00 r10 r20 | r01 r11 r21) made a rotation by Gram–Schmidt, R = Rz(yaw) Ry(pitch) Rx(roll) read back as
    # angles, against the held-out truth, angle differences wrapped to (−π, π]
    mu = torch.load(path, weights_only=True)["normalization"]["target_mean"]
    c1, c2 = np.array(mu[3:6]), np.array(mu[6:9])
    a = c1 / np.linalg.norm(c1)
    b = c2 - (a @ c2) * a
    b /= np.linalg.norm(b)
    R = np.stack([a, b, np.cross(a, b)], 1)
    avg = np.array(mu[:3] + [math.atan2(R[1, 0], R[0, 0]), math.asin(-R[2, 0]), math.atan2(R[2, 1], R[2, 2])])
    from risp_data.shards import iter_wds

    truth = np.stack([s["state"] for s in iter_wds(shards["held_out"])])
    d = avg[None] - truth
    d[:, 3:] = (d[:, 3:] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(res["results"]["average"]["per_dim_mae"], np.abs(d).mean(0), rtol=1e-9)
    assert res["results"]["average"]["mean"] == pytest.approx(np.abs(d).mean(), rel=1e-9)  # the paper's L1
    from importlib.metadata import version

    from risp_data.shards.manifest import sha256_file

    assert res["model_sha256"] == sha256_file(path) and res["versions"]["risp"] == version("risp")
    assert json.load(open(os.path.join(os.path.dirname(path), "config.json")))["versions"]["torch"]
    from risp_data.shards.manifest import risp_commit

    # the checkout's commit, as task results record it (a run names the code that trained and evaluated it)
    commit = json.load(open(os.path.join(os.path.dirname(path), "config.json")))["versions"]["risp_commit"]
    assert commit == risp_commit() == res["versions"]["risp_commit"]
    # the run folder names its model.pt; the default results land beside it
    run = os.path.dirname(path)
    r = CliRunner().invoke(cli, ["eval", run, shards["held_out"], "--quiet", "--limit", "4"])
    assert r.exit_code == 0, r.output
    assert [json.load(open(os.path.join(run, f)))["n"] for f in os.listdir(run) if f.startswith("eval-") and f.endswith(".json")] == [4]


@pytest.mark.parametrize("fmt", ["wds", "zarr"])
def test_resume_after_kill_gives_identical_weights(shards, tmp_path, fmt):
    """Uninterrupted run vs. a run killed mid-epoch (after a step-checkpoint) and resumed: same weights."""
    kw = dict(reg="stochastic", gamma=0.5, epochs=2, batch_size=8, checkpoint_every=3, format=fmt,
              workers=2 if fmt == "wds" else 0)
    a = fit(_cfg(shards, tmp_path / "a", **kw), progress=False)
    cfg_b = _cfg(shards, tmp_path / "b", **kw)
    with pytest.raises(TrainingStopped):
        fit(cfg_b, progress=False, stop_after_step=13)  # epochs of 8 steps: last checkpoint at step 12
    ck = torch.load(tmp_path / "b" / "last.pt", weights_only=True)
    assert ck["progress"]["global_step"] == 12 and ck["progress"]["epoch"] == 1 and ck["progress"]["batch"] == 4
    with pytest.raises(RispError, match="--resume"):
        fit(cfg_b, progress=False)
    b = fit(cfg_b, resume=True, progress=False)
    wa = torch.load(a, weights_only=True)["model"]
    wb = torch.load(b, weights_only=True)["model"]
    for k in wa:
        torch.testing.assert_close(wa[k], wb[k], rtol=0, atol=0, msg=k)
    rows_a = open(tmp_path / "a" / "losses.csv").read().splitlines()
    rows_b = open(tmp_path / "b" / "losses.csv").read().splitlines()
    assert [r.split(",")[:8] for r in rows_a] == [r.split(",")[:8] for r in rows_b]


def test_resume_continues_the_checkpoints_architecture(shards, tmp_path, monkeypatch):
    """A run checkpointed under one automatic-stem rule and resumed under another (a newer risp) finishes with the
    network it started (the stem's weights have another shape: loading them into the new stem would fail)."""
    from risp_train import train as train_mod

    cfg = _cfg(shards, tmp_path / "run", epochs=2, batch_size=8, checkpoint_every=3)
    with pytest.raises(TrainingStopped):
        fit(cfg, progress=False, stop_after_step=5)
    assert torch.load(tmp_path / "run" / "last.pt", weights_only=True)["model_config"]["stem"] == "small"
    monkeypatch.setattr(train_mod, "stem_for_resolution", lambda resolution: "stride2")
    model = fit(cfg, resume=True, progress=False)
    ck = torch.load(model, weights_only=True)
    assert ck["model_config"]["stem"] == "small" and ck["progress"]["complete"]
    assert ck["model"]["stem.0.weight"].shape[-1] == 3 and ck["progress"]["global_step"] == 16


def test_exact_and_surrogate_train_one_epoch(shards, tmp_path):
    for reg in ("exact", "surrogate"):
        path = fit(_cfg(shards, tmp_path / reg, reg=reg, epochs=1, batch_size=16), progress=False)
        ck = torch.load(path, weights_only=True)
        from risp_train.config import GAMMA_DEFAULTS

        assert ck["config"]["reg"] == reg and ck["gamma"] == pytest.approx(GAMMA_DEFAULTS["cube"])  # calibrated γ
        assert ck["history"][-1]["train_reg"] > 0  # the form was evaluated (0 would be a regularizer never run)


def test_gamma_start_keeps_the_regularizer_off_then_on(shards, tmp_path):
    """--gamma-start 0.5: the logged γ(t) and R are 0 in the first half of the steps (R is not computed), R is
    measured (> 0) once γ(t) > 0."""
    import csv

    fit(_cfg(shards, tmp_path / "late", reg="stochastic", epochs=2, batch_size=8, gamma_start=0.5),
        progress=False)
    rows = list(csv.DictReader(open(tmp_path / "late" / "losses.csv")))
    n = len(rows)
    assert n == 16
    early, late = rows[: n // 2], rows[n // 2 + 1:]
    assert all(float(r["gamma"]) == 0.0 and float(r["reg"]) == 0.0 for r in early)
    assert all(float(r["gamma"]) > 0.0 and float(r["reg"]) > 0.0 for r in late)


def _copy(src, dst):
    shutil.copytree(src, dst)
    return str(dst)


def test_clear_errors(shards, tmp_path):
    runner = CliRunner()
    # corrupt shard: flip bytes inside a tar (size unchanged, so only decoding/checksums can notice)
    bad = _copy(shards["train"], tmp_path / "corrupt")
    tar = os.path.join(bad, "wds", "shard-000001.tar")
    data = bytearray(open(tar, "rb").read())
    data[2000:2400] = bytes(400)
    open(tar, "wb").write(bytes(data))
    r = runner.invoke(cli, ["fit", bad, "--out", str(tmp_path / "r1"), "--epochs", "1", "--width", "4",
                            "--workers", "0", "--batch-size", "4", "--quiet"])
    assert r.exit_code != 0 and "shard-000001.tar" in r.output and "Error" in r.output, r.output
    # the same read by a DataLoader worker process (the default): torch re-raises it with the worker's whole
    # traceback in the message; the user still gets the one line
    r = runner.invoke(cli, ["fit", bad, "--out", str(tmp_path / "r1w"), "--epochs", "1", "--width", "4",
                            "--workers", "1", "--batch-size", "4", "--quiet"])
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code != 0 and "Traceback" not in r.output and "Caught" not in r.output, r.output
    assert lines[-1].startswith("Error: ") and "shard-000001.tar" in lines[-1], r.output
    assert not any(ln.startswith("Error") for ln in lines[:-1]), r.output
    # empty shard list
    empty = _copy(shards["held_out"], tmp_path / "empty")
    m = json.load(open(os.path.join(empty, "manifest.json")))
    m["shards"] = []
    json.dump(m, open(os.path.join(empty, "manifest.json"), "w"))
    r = runner.invoke(cli, ["fit", empty, "--out", str(tmp_path / "r2"), "--quiet"])
    assert r.exit_code != 0 and "no complete shards" in r.output, r.output
    # mismatched state dimension
    mism = _copy(shards["held_out"], tmp_path / "mism")
    m = json.load(open(os.path.join(mism, "manifest.json")))
    m["state_names"] = m["state_names"][:5]
    json.dump(m, open(os.path.join(mism, "manifest.json"), "w"))
    r = runner.invoke(cli, ["fit", mism, "--out", str(tmp_path / "r3"), "--quiet"])
    assert r.exit_code != 0 and "state dimension" in r.output, r.output
    # regularizer on shards without Jacobians; unknown regularizer
    r = runner.invoke(cli, ["fit", shards["held_out"], "--out", str(tmp_path / "r4"), "--reg", "exact", "--quiet"])
    assert r.exit_code != 0 and "Jacobians" in r.output and "--reg none" in r.output, r.output
    r = runner.invoke(cli, ["fit", shards["held_out"], "--out", str(tmp_path / "r5"), "--reg", "bogus"])
    assert r.exit_code != 0 and "Invalid value for '--reg': 'bogus' is not one of 'none', 'surrogate'" in r.output
    r = runner.invoke(cli, ["fit", shards["train"], "--out", str(tmp_path / "r5b"), "--gamma-start", "1.5"])
    assert r.exit_code != 0 and "--gamma-start must be in [0, 1)" in r.output and not os.path.exists(tmp_path / "r5b")
    # checkpoint from another environment
    model = fit(_cfg(shards, tmp_path / "tiny", epochs=1, batch_size=16), progress=False)
    ck = torch.load(model, weights_only=True)
    ck["env"] = "quadrotor"
    other = str(tmp_path / "other-env.pt")
    torch.save(ck, other)
    r = runner.invoke(cli, ["eval", other, shards["held_out"], "--quiet"])
    assert r.exit_code != 0 and "environment 'quadrotor'" in r.output, r.output
    # not a checkpoint at all
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    r = runner.invoke(cli, ["eval", str(junk), shards["held_out"], "--quiet"])
    assert r.exit_code != 0 and "is a text file (it begins 'not a checkpoint')" in r.output, r.output


def test_cli_error_is_one_line_with_nonzero_exit(tmp_path):
    r = subprocess.run([sys.executable, "-m", "risp_train", "eval", str(tmp_path / "missing.pt"), str(tmp_path)],
                       capture_output=True, text=True)
    assert r.returncode == 1
    assert r.stderr.strip().count("\n") == 0 and r.stderr.lower().startswith("error: "), r.stderr
    assert "checkpoint not found" in r.stderr


@pytest.mark.slow
@pytest.mark.parametrize("cache", ["stream", "memory"])
def test_torchrun_two_processes_train_one_network(shards, tmp_path, cache):
    """Two gloo ranks, each on its own samples, end every epoch with bit-equal weights (both cache paths)."""
    from risp_train.train import weights_digest

    out = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",  # a free port
           "-m", "risp_train", "fit", shards["train"], "--out", str(out), "--preset", "cpu", "--epochs", "2",
           "--batch-size", "4", "--width", "4", "--workers", "1", "--reg", "stochastic", "--cache", cache,
           "--quiet"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    ck = torch.load(out / "model.pt", weights_only=True)
    assert ck["world_size"] == 2 and ck["cache"] == cache
    # 4 shards of 16 → 2 per rank (stream: 1 worker) or 32 samples per rank (memory): 8 steps per epoch each
    assert ck["progress"]["global_step"] == 16
    digests = ck["rank_weights_sha256"]
    assert len(digests) == 2 and digests[0] == digests[1]  # rank 1 holds the very weights rank 0 saved
    assert weights_digest(ck["model"]) == digests[0]  # the saved weights are the ones the ranks compared
    # the digest tells trainings apart: one process on all the samples (other batches) ends elsewhere
    single = tmp_path / "single"
    r1 = CliRunner().invoke(cli, ["fit", shards["train"], "--out", str(single), "--preset", "cpu", "--epochs", "2",
                                  "--batch-size", "4", "--width", "4", "--workers", "1", "--reg", "stochastic",
                                  "--cache", cache, "--quiet"])
    assert r1.exit_code == 0, r1.output
    assert torch.load(single / "model.pt", weights_only=True)["rank_weights_sha256"][0] != digests[0]


@contextlib.contextmanager
def _file_store_group(rank: int, world: int, store_path: str):
    """A spawned worker's own gloo group, rendezvousing through a file (no port to race for), destroyed after."""
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", store=dist.FileStore(store_path, world), rank=rank, world_size=world)
    try:
        yield
    finally:
        dist.destroy_process_group()


def _agreement_worker(rank: int, world: int, store_path: str, diverge: bool, results: str) -> None:
    from risp_train.train import check_ranks_agree, rank_digests

    with _file_store_group(rank, world, store_path):
        torch.manual_seed(rank if diverge else 0)
        net = torch.nn.Linear(3, 2)
        try:
            check_ranks_agree(rank_digests(net, world), epoch=0)
            outcome = "ok"
        except RispError as e:
            outcome = str(e)
        with open(os.path.join(results, f"rank{rank}.txt"), "w") as f:
            f.write(outcome)


@pytest.mark.parametrize("diverge", [False, True])
def test_diverged_ranks_are_refused_on_every_rank(tmp_path, diverge):
    import torch.multiprocessing as mp

    mp.start_processes(_agreement_worker, args=(2, str(tmp_path / "store"), diverge, str(tmp_path)), nprocs=2,
                       join=True, start_method="spawn")
    outcomes = [(tmp_path / f"rank{r}.txt").read_text() for r in range(2)]
    if diverge:  # both ranks raise together (neither is left waiting in a collective)
        assert all("torchrun ranks' weights differ after epoch 0" in o for o in outcomes), outcomes
    else:
        assert outcomes == ["ok", "ok"]


def _two_rank_fit_worker(rank: int, world: int, store: str, cfgs, results: str, nudge: bool) -> None:
    """One rank of real two-rank fits, run one after the other in this process; with ``nudge``, rank 1 adds 1e-6 to
    one gradient entry after the all-reduce. Writes each fit's outcome, the notes fit echoed, and whether the
    process group is left once the exit handlers ran. fit creates the group itself (and so owns it),
    rendezvousing through a FileStore rather than a TCP port (no free-port race)."""
    import atexit
    import faulthandler

    import torch.distributed as dist

    import risp_train.train as train_mod

    faulthandler.enable()  # a native abort (SIGABRT) prints every thread's Python stack to the test's output
    os.environ.update(WORLD_SIZE=str(world), RANK=str(rank), LOCAL_RANK=str(rank), LOCAL_WORLD_SIZE=str(world))
    torch.set_num_threads(1)
    real_init = dist.init_process_group
    dist.init_process_group = lambda backend, **kw: real_init(backend, store=dist.FileStore(store, world), rank=rank,
                                                              world_size=world)
    if nudge and rank == 1:
        real = train_mod.allreduce_gradients

        def nudged(params, world_size):
            real(params, world_size)
            params[0].grad.view(-1)[0] += 1e-6

        train_mod.allreduce_gradients = nudged
    lines, notes = [], []
    for cfg in cfgs:
        try:
            fit(cfg, progress=False, echo=notes.append)
            lines.append("finished")
        except RispError as e:
            lines.append(str(e))
    atexit._run_exitfuncs()  # what the interpreter runs at exit, before its teardown
    with open(os.path.join(results, f"fit{rank}.txt"), "w") as f:
        f.write("\n".join(lines + [f"notes: {len(notes)}", f"group left: {dist.is_initialized()}"]))


def _two_rank_fit(cfgs, tmp_path, nudge: bool) -> list[list[str]]:
    import torch.multiprocessing as mp

    store = tmp_path / f"store-{'nudged' if nudge else 'same'}"  # one fresh FileStore per pair of processes
    mp.start_processes(_two_rank_fit_worker, args=(2, str(store), cfgs, str(tmp_path), nudge), nprocs=2, join=True,
                       start_method="spawn")
    return [(tmp_path / f"fit{r}.txt").read_text().splitlines() for r in range(2)]


@pytest.mark.slow
def test_a_fit_whose_ranks_diverge_stops_at_the_epoch_end(shards, tmp_path):
    """The check is wired into the loop: two ranks of a real fit whose weights drift apart (rank 1's gradient
    nudged) both stop after epoch 0, before its checkpoint; no last.pt or model.pt claims a trained network.
    The group fit created is destroyed by the exit handlers (left to interpreter shutdown, gloo can abort the
    process: pytorch/pytorch#190489), not when fit returns: a second fit in the process reuses it."""
    out = tmp_path / "diverged"
    outcomes = _two_rank_fit([_cfg(shards, out, epochs=2, cache="memory", checkpoint_every=0)], tmp_path, nudge=True)
    assert all("torchrun ranks' weights differ after epoch 0" in o[0] for o in outcomes), outcomes
    assert not (out / "last.pt").exists() and not (out / "model.pt").exists()
    assert [o[1:] for o in outcomes] == [["notes: 0", "group left: False"]] * 2
    # without the nudge, two fits one after the other in the same processes: both finish (the second reuses the
    # group), and nothing is resynced
    cfgs = [_cfg(shards, tmp_path / f"same{i}", epochs=1, cache="memory", checkpoint_every=0) for i in range(2)]
    outcomes = _two_rank_fit(cfgs, tmp_path, nudge=False)
    assert outcomes == [["finished", "finished", "notes: 0", "group left: False"]] * 2, outcomes
    for i in range(2):
        assert torch.load(tmp_path / f"same{i}" / "model.pt", weights_only=True)["rank_resyncs"] == []


@pytest.mark.slow
def test_resync_gives_drifting_ranks_rank0s_weights_at_every_epoch_end(shards, tmp_path):
    """--rank-check resync (nodes whose CPUs round differently): the same drifting ranks as above finish; at each
    epoch end rank 1 takes rank 0's weights and optimizer state, so the digests compared (and checkpointed) agree,
    rank 0 says so once per event, and the checkpoint records each resync with the digests that differed."""
    out = tmp_path / "resynced"
    cfg = _cfg(shards, out, epochs=2, cache="memory", checkpoint_every=0, rank_check="resync")
    outcomes = _two_rank_fit([cfg], tmp_path, nudge=True)
    assert outcomes == [["finished", "notes: 2", "group left: False"],
                        ["finished", "notes: 0", "group left: False"]], outcomes
    ck = torch.load(out / "model.pt", weights_only=True)
    assert [r["epoch"] for r in ck["rank_resyncs"]] == [0, 1]  # rank 1 drifts again in every epoch
    for r in ck["rank_resyncs"]:
        assert len(set(r["rank_weights_sha256"])) == 2  # they did differ before the broadcast
    from risp_train.train import weights_digest

    final = ck["rank_weights_sha256"]
    assert final[0] == final[1] == weights_digest(ck["model"])  # after it both held the saved weights


def _optimizer_digest(opt) -> str:
    from risp_train.train import weights_digest

    sd = opt.state_dict()
    flat = {f"{p}.{k}": (v if torch.is_tensor(v) else torch.tensor(v)) for p, st in sd["state"].items()
            for k, v in st.items()}
    return weights_digest(flat)


def _broadcast_worker(rank: int, world: int, store_path: str, results: str) -> None:
    from risp_train.train import broadcast_rank0_state, weights_digest

    with _file_store_group(rank, world, store_path):
        torch.manual_seed(rank)  # other weights, and Adam states of other steps and moments
        net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4), torch.nn.Linear(4, 2))
        opt = torch.optim.Adam(net.parameters(), lr=1e-2)
        for _ in range(rank + 1):
            net(torch.randn(5, 3)).square().sum().backward()
            opt.step()
        before = (weights_digest(net.state_dict()), _optimizer_digest(opt))
        broadcast_rank0_state(net, opt)
        after = (weights_digest(net.state_dict()), _optimizer_digest(opt))
        with open(os.path.join(results, f"b{rank}.json"), "w") as f:
            json.dump({"before": before, "after": after}, f)


def test_broadcast_gives_every_rank_rank0s_weights_buffers_and_adam_state(tmp_path):
    import torch.multiprocessing as mp

    mp.start_processes(_broadcast_worker, args=(2, str(tmp_path / "store"), str(tmp_path)), nprocs=2, join=True,
                       start_method="spawn")
    r0, r1 = (json.loads((tmp_path / f"b{r}.json").read_text()) for r in range(2))
    assert r0["before"][0] != r1["before"][0] and r0["before"][1] != r1["before"][1]  # they did differ
    assert r0["after"] == r0["before"]  # rank 0 keeps its own
    assert r1["after"] == r0["before"]  # rank 1 now holds rank 0's weights, BatchNorm statistics and Adam moments


def test_unknown_rank_check_is_one_error_line(shards, tmp_path):
    r = CliRunner().invoke(cli, ["fit", shards["train"], "--out", str(tmp_path / "r"), "--rank-check", "warn",
                                 "--quiet"])
    assert r.exit_code != 0 and "unknown --rank-check 'warn'; choose one of: stop, resync" in r.output, r.output
    assert not (tmp_path / "r").exists()


def test_weights_digest_sees_a_one_ulp_change():
    from risp_train.train import weights_digest

    net = torch.nn.Linear(4, 3)
    before = weights_digest(net.state_dict())
    assert weights_digest(net.state_dict()) == before
    with torch.no_grad():
        net.weight[1, 2] = torch.nextafter(net.weight[1, 2], torch.tensor(float("inf")))
    assert weights_digest(net.state_dict()) != before
    # any dtype (numpy has no bfloat16): the bytes are hashed, and the dtype with them
    bf = {"w": torch.ones(3, dtype=torch.bfloat16)}
    assert weights_digest(bf) != weights_digest({"w": torch.ones(3, dtype=torch.float16)})


@pytest.mark.slow
def test_resume_after_sigkill(shards, tmp_path):
    """A real kill (SIGKILL of the training process) after a step checkpoint; --resume finishes the run."""
    import signal
    import time

    # four epochs: the kill must land before the run ends, however fast the machine (it is sent at step >= 2)
    args = ["fit", shards["train"], "--preset", "cpu", "--epochs", "4", "--batch-size", "4", "--width", "4",
            "--workers", "1", "--reg", "stochastic", "--gamma", "0.5", "--checkpoint-every", "2", "--quiet"]
    ref = CliRunner().invoke(cli, args + ["--out", str(tmp_path / "ref")])
    assert ref.exit_code == 0, ref.output
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "risp_train", *args, "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.time() + 240
        while time.time() < deadline and proc.poll() is None:
            if (out / "last.pt").exists():
                ck = torch.load(out / "last.pt", weights_only=True)
                if ck["progress"]["global_step"] >= 2:
                    break
            time.sleep(0.02)
        assert proc.poll() is None, "the run finished before it could be killed"
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    r = CliRunner().invoke(cli, args + ["--out", str(out), "--resume"])
    assert r.exit_code == 0, r.output
    wa = torch.load(tmp_path / "ref" / "model.pt", weights_only=True)["model"]
    wb = torch.load(out / "model.pt", weights_only=True)["model"]
    for k in wa:
        torch.testing.assert_close(wa[k], wb[k], rtol=0, atol=0, msg=k)


def test_fit_sets_its_thread_count_and_gives_it_back(shards, tmp_path):
    caller = torch.get_num_threads()
    torch.set_num_threads(2)  # the caller's setting differs from the run's
    seen = []
    import risp_train.train as train_mod

    real = train_mod.risp_loss

    def spy(*args, **kw):  # the thread count in force while a training step computes
        seen.append(torch.get_num_threads())
        return real(*args, **kw)

    train_mod.risp_loss = spy
    try:
        path = fit(_cfg(shards, tmp_path / "t", epochs=1, threads=1), progress=False)
    finally:
        train_mod.risp_loss = real
        after = torch.get_num_threads()
        torch.set_num_threads(caller)
    assert seen and set(seen) == {1}  # every step used the requested count…
    assert after == 2  # …and the caller's setting is back
    assert torch.load(path, weights_only=True)["threads"] == 1
    assert json.load(open(tmp_path / "t" / "config.json"))["threads"] == 1


def test_default_threads_leave_cpus_only_for_the_workers_that_start(shards, tmp_path, monkeypatch):
    """Streaming 4 webdataset shards, --workers 6 starts 4 workers (one shard each at least): the default thread
    count leaves 4 CPUs to them, not 6 (with 7 CPUs: 3 threads, not 1)."""
    from risp_data import threads
    from risp_train.data import open_shards

    monkeypatch.setattr(threads, "available_cpus", lambda: 7)
    assert len(open_shards(shards["train"], "wds").counts) == 4
    caller = torch.get_num_threads()
    try:
        path = fit(_cfg(shards, tmp_path / "t", epochs=1, workers=6, threads=0, cache="stream", format="wds"),
                   progress=False)
    finally:
        torch.set_num_threads(caller)
    assert torch.load(path, weights_only=True)["threads"] == 3


def test_the_regularizer_scales_psi_by_the_shards_own_domain(tmp_path, monkeypatch):
    """Target-domain training shards (with Jacobians) are regularized with the target domain's σ_ψ, not the train
    domain's: the manifest's domain reaches psi_scale."""
    import risp_train.train as train_mod

    seen, real = [], train_mod.psi_scale
    monkeypatch.setattr(train_mod, "psi_scale", lambda env, domain="train": seen.append((env, domain)) or real(env, domain))
    target = _render(tmp_path / "target", 8, 8, 3, ("--domain", "target"))
    cfg = make_config(target, str(tmp_path / "t"), preset="cpu", epochs=2, batch_size=4, width=4, workers=0,
                      stats_samples=8, reg="stochastic", checkpoint_every=1)
    with pytest.raises(TrainingStopped):
        fit(cfg, progress=False, stop_after_step=2)
    assert seen == [("cube", "target")]
    last = tmp_path / "t" / "last.pt"
    ck = torch.load(last, weights_only=True)
    assert ck["psi_std"] == real("cube", "target").tolist()
    # a resumed run keeps the σ_ψ it began with: a checkpoint from before σ_ψ followed the domain (no psi_std)
    # continues with the train domain's
    used, loss = [], train_mod.risp_loss
    monkeypatch.setattr(train_mod, "risp_loss", lambda *a, **k: used.append(a[-1].tolist()) or loss(*a, **k))
    del ck["psi_std"]
    torch.save(ck, last)
    fit(cfg, resume=True, progress=False)
    assert used and all(u == real("cube", "train").tolist() for u in used)


@pytest.mark.parametrize("cache", ["stream", "memory"])
def test_fit_leaves_the_callers_rng_alone(shards, tmp_path, cache):
    """fit() draws nothing from torch's global generator (a DataLoader pass used to draw its base seed there)."""
    torch.manual_seed(1234)
    before = torch.random.get_rng_state()
    fit(_cfg(shards, tmp_path / "t", epochs=1, cache=cache), progress=False)
    assert torch.equal(torch.random.get_rng_state(), before)


@pytest.mark.parametrize("args, message", [(["--threads", "-1"], "--threads"), (["--device", "tpu:x"], "unknown --device")])
def test_fit_refuses_bad_threads_or_device_before_writing(shards, tmp_path, args, message):
    out = tmp_path / "run"
    r = CliRunner().invoke(cli, ["fit", shards["train"], "--out", str(out), "--quiet", *args])
    assert r.exit_code != 0 and message in r.output, r.output
    assert not out.exists()  # nothing written


def test_resume_compares_resolved_options(shards, tmp_path):
    """--gamma / --gamma-start equal to the environment's defaults resume a run started without them (the
    startup line says the same γ); another value is refused, before the data set is decoded."""
    from risp_train.config import GAMMA_DEFAULTS, GAMMA_START_DEFAULTS

    kw = dict(reg="stochastic", epochs=2, batch_size=8, checkpoint_every=3)
    with pytest.raises(TrainingStopped):
        fit(_cfg(shards, tmp_path / "r", **kw), progress=False, stop_after_step=5)
    same = _cfg(shards, tmp_path / "r", gamma=GAMMA_DEFAULTS["cube"],
                gamma_start=GAMMA_START_DEFAULTS.get("cube", 0.0), **kw)
    with pytest.raises(RispError, match=r"different options: gamma=.*→0\.123"):
        fit(_cfg(shards, tmp_path / "r", gamma=0.123, **kw), resume=True, progress=False)
    assert os.path.isfile(fit(same, resume=True, progress=False))


def test_resume_refuses_another_held_out_set(shards, tmp_path):
    """The history's val_error is one curve: a run begun with --val resumes only with the same held-out shards
    (not with others, not without), and a run begun without --val does not resume with one."""
    other = _render(tmp_path / "other_val", 32, 16, 12, ("--format", "wds", "--no-jacobian"))
    kw = dict(reg="none", epochs=2, batch_size=8, checkpoint_every=3)
    with pytest.raises(TrainingStopped):
        fit(_cfg(shards, tmp_path / "v", val=shards["held_out"], **kw), progress=False, stop_after_step=5)
    with pytest.raises(RispError, match="validated on other shards"):
        fit(_cfg(shards, tmp_path / "v", val=other, **kw), resume=True, progress=False)
    with pytest.raises(RispError, match="without --val: it was trained with --val"):
        fit(_cfg(shards, tmp_path / "v", **kw), resume=True, progress=False)
    assert os.path.isfile(fit(_cfg(shards, tmp_path / "v", val=shards["held_out"], **kw), resume=True,
                              progress=False))
    vals = [h["val_error"] for h in json.load(open(tmp_path / "v" / "history.json")) if "val_error" in h]
    assert len(vals) == 3  # before training and after each of the two epochs, all on the same images

    with pytest.raises(TrainingStopped):
        fit(_cfg(shards, tmp_path / "n", **kw), progress=False, stop_after_step=5)
    with pytest.raises(RispError, match="trained without a held-out set"):
        fit(_cfg(shards, tmp_path / "n", val=shards["held_out"], **kw), resume=True, progress=False)


def test_resume_of_a_finished_run_trains_nothing_and_keeps_model_pt(shards, tmp_path):
    """--resume of a complete run: a note says so, and model.pt keeps its bytes (it used to be written again, with
    a new checksum that no longer matched the task results recording it); more epochs are another run."""
    from risp_data.shards.manifest import sha256_file

    out = tmp_path / "done"
    args = ["fit", shards["train"], "--out", str(out), "--quiet", "--epochs", "1", "--batch-size", "8",
            "--width", "4", "--workers", "0", "--reg", "none"]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    before = sha256_file(str(out / "model.pt")), os.path.getmtime(out / "model.pt"), os.path.getmtime(out / "last.pt")
    r = CliRunner().invoke(cli, args + ["--resume"])
    assert r.exit_code == 0, r.output
    assert f"note: the run in {out} is already complete (1 epochs): nothing trained, model.pt unchanged" in r.output
    assert (sha256_file(str(out / "model.pt")), os.path.getmtime(out / "model.pt"),
            os.path.getmtime(out / "last.pt")) == before
    r = CliRunner().invoke(cli, [a if a != "1" else "2" for a in args] + ["--resume"])
    assert r.exit_code != 0 and "different options: epochs=1→2" in r.output, r.output


def test_resume_keeps_the_gamma_the_run_trained_with(shards, tmp_path, monkeypatch):
    """A default γ changed between a run's start and its resume (the hand's went 0.3 → 0.05) is refused, not taken
    over silently: the checkpoint's own γ is what the resume is compared with."""
    import risp_train.config as config

    kw = dict(reg="stochastic", epochs=2, batch_size=8, checkpoint_every=3)
    with pytest.raises(TrainingStopped):
        fit(_cfg(shards, tmp_path / "r", **kw), progress=False, stop_after_step=5)
    was = config.GAMMA_DEFAULTS["cube"]
    monkeypatch.setitem(config.GAMMA_DEFAULTS, "cube", was / 2)
    with pytest.raises(RispError, match=rf"different options: gamma={was!r}→{was / 2!r}"):
        fit(_cfg(shards, tmp_path / "r", **kw), resume=True, progress=False)
    assert os.path.isfile(fit(_cfg(shards, tmp_path / "r", gamma=was, **kw), resume=True, progress=False))


def test_option_changes_reads_the_stored_runs_own_gamma():
    """option_changes against a run's record: its γ and γ start win over today's defaults; a record from before the
    late start ramped from step 0; without a regularizer on either side γ's start is not compared."""
    from risp_train.config import GAMMA_DEFAULTS, GAMMA_START_DEFAULTS
    from risp_train.train import option_changes

    stored = make_config("shards", "out", preset="cpu", reg="stochastic").to_dict()  # γ, start: the defaults then
    today = make_config("shards", "out", preset="cpu", reg="stochastic")
    assert option_changes(stored, today, "hand") == []  # nothing recorded: compared as resolved today
    old_hand = {"gamma": 0.3, "gamma_start": 0.0}
    assert option_changes(stored, today, "hand", used=old_hand) == [f"gamma=0.3→{GAMMA_DEFAULTS['hand']!r}"]
    assert option_changes(stored, make_config("shards", "out", preset="cpu", reg="stochastic", gamma=0.3), "hand",
                          used=old_hand) == []
    before_late_start = {"gamma": GAMMA_DEFAULTS["cube"]}  # no gamma_start: the ramp began at the first step
    assert option_changes(stored, today, "cube", used=before_late_start) == [
        f"gamma_start=0.0→{GAMMA_START_DEFAULTS['cube']!r}"]
    own_start = {**stored, "gamma_start": 0.3}  # --gamma-start stored only in the config (before the record had it)
    assert option_changes(own_start, make_config("shards", "out", preset="cpu", reg="stochastic", gamma_start=0.3),
                          "cube", used=before_late_start) == []
    plain = make_config("shards", "out", preset="cpu", reg="none")
    assert option_changes(plain.to_dict(), plain, "cube", used={"gamma": 0.0}) == []


def test_images_too_small_for_the_network_are_refused_before_a_run_folder(tmp_path):
    small = _render(tmp_path / "tiny", 8, 8, 0, ("--res", "8"))
    out = tmp_path / "run"
    cfg = make_config(small, str(out), preset="cpu", epochs=1, batch_size=4, width=4, workers=0)
    with pytest.raises(RispError, match=r"8×8 images are too small for the network \(stem 'small' needs at least "
                                        r"9×9\); render them with --res 9 or more"):
        fit(cfg, progress=False)
    assert not out.exists()


def test_each_rank_streams_its_own_shards_as_the_step_plan_counts(shards):
    """Rank r of W reads the epoch's shards r, r + W, … from its own rank and world size (not the environment's):
    the ranks' samples are disjoint, together every sample once, and each rank has the batches steps_per_epoch
    planned for it."""
    from risp_train.data import ShardSet, WdsStream, epoch_shard_order, open_shards, steps_per_epoch

    s: ShardSet = open_shards(shards["train"], "wds")
    assert len(s.urls) == 4
    keys = {}
    for rank in (0, 1):
        stream = WdsStream(s.urls, seed=3, epoch=1, shuffle_buffer=0, need_jacobian=False, rank=rank, world_size=2,
                           resolution=s.resolution)
        keys[rank] = [d["key"] for d in stream]
    assert not set(keys[0]) & set(keys[1])
    assert len(keys[0]) + len(keys[1]) == s.num_samples == len(set(keys[0]) | set(keys[1]))
    order = epoch_shard_order(len(s.urls), 3, 1)
    for rank in (0, 1):
        assert len(keys[rank]) == sum(s.counts[i] for i in order[rank::2])
    assert steps_per_epoch(s, 3, 1, 4, 2, 0) == min(len(k) // 4 for k in keys.values())
