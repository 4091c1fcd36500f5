"""risp-train's in-memory training data (risp_train/memory.py) on tiny real shards.

What must hold: the decoded tensors are the streamed samples, value for value, in either shard format; a run
from memory is bitwise the run that streams the zarr store (same batch plan); it resumes bitwise; ``auto``
falls back to streaming when memory is short; damage is one clear error, as on the streamed path.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from risp_data.errors import RispError
from risp_train.config import make_config
from risp_train.data import iter_batches, map_style_steps, open_shards
from risp_train.memory import estimate_bytes, load_memory_set, memory_batches, resolve_cache
from risp_train.train import TrainingStopped, fit

from test_train_pipeline import _render


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    root = tmp_path_factory.mktemp("memory-shards")
    return {"train": _render(root / "train", 48, 16, 5), "root": root}


def _cfg(shards, out, **kw):
    base = dict(epochs=2, batch_size=8, width=4, workers=0, lr=3e-3, shuffle_buffer=8, stats_samples=32,
                reg="stochastic", gamma=0.5, threads=1)  # one thread whatever the workers: bitwise comparisons
    base.update(kw)
    return make_config(shards["train"], str(out), preset="cpu", **base)


def _weights(path):
    return torch.load(path, weights_only=True)["model"]


def _assert_same_weights(a, b):
    wa, wb = _weights(a), _weights(b)
    assert wa.keys() == wb.keys()
    for k in wa:
        torch.testing.assert_close(wa[k], wb[k], rtol=0, atol=0, msg=k)


@pytest.mark.parametrize("fmt, workers", [("wds", 0), ("wds", 2), ("zarr", 1)])
def test_memory_set_holds_the_streamed_samples(shards, fmt, workers):
    s = open_shards(shards["train"], fmt)
    m = load_memory_set(s, need_jacobian=True, workers=workers, state_dim=6)
    assert len(m) == 48 and m.nbytes == estimate_bytes(s, True)
    assert m.keys == tuple(f"s{i:08d}" for i in range(48))  # shard order, as the zarr store counts
    streamed = {}
    for b in iter_batches(s, 7, need_jacobian=True, state_dim=6):
        for i, key in enumerate(b["key"]):
            streamed[key] = {f: b[f][i] for f in ("image", "state", "psi", "jacobian")}
    assert set(streamed) == set(m.keys)
    for p, key in enumerate(m.keys):
        for f, t in (("image", m.image), ("state", m.state), ("psi", m.psi), ("jacobian", m.jacobian)):
            torch.testing.assert_close(t[p], streamed[key][f], rtol=0, atol=0, msg=f"{key} {f}")
    assert m.jacobian.abs().sum() > 0 and m.image.dtype == torch.float32 and m.state.dtype == torch.float64


def test_memory_batches_are_the_zarr_plan_and_cover_an_epoch(shards):
    m = load_memory_set(open_shards(shards["train"]), need_jacobian=False)
    assert m.jacobian is None
    for world in (1, 2):
        steps = map_style_steps(len(m), 8, world)
        seen = []
        for rank in range(world):
            batches = list(memory_batches(m, seed=3, epoch=1, batch_size=8, rank=rank, world_size=world))
            assert len(batches) == steps and all(len(b["key"]) == 8 for b in batches)
            seen += [k for b in batches for k in b["key"]]
        assert len(seen) == len(set(seen)) == steps * 8 * world  # no sample twice within an epoch
    order = lambda e: [k for b in memory_batches(m, seed=3, epoch=e, batch_size=8) for k in b["key"]]  # noqa: E731
    assert order(0) != order(1) and order(1) == order(1)  # a new permutation per epoch, a fixed one per (seed, epoch)


def test_training_from_memory_is_the_zarr_stream_run(shards, tmp_path):
    """Same batch plan, same decoded values → bitwise the same network as streaming the zarr store."""
    streamed = fit(_cfg(shards, tmp_path / "zs", format="zarr", cache="stream"), progress=False)
    memory = fit(_cfg(shards, tmp_path / "zm", format="zarr", cache="memory"), progress=False)
    from_wds = fit(_cfg(shards, tmp_path / "wm", format="wds", cache="memory", workers=2), progress=False)
    _assert_same_weights(streamed, memory)
    _assert_same_weights(memory, from_wds)  # the two formats decode to the same floats
    assert json.load(open(tmp_path / "zm" / "config.json"))["cache"] == "memory"
    assert torch.load(memory, weights_only=True)["cache"] == "memory"
    assert json.load(open(tmp_path / "zs" / "config.json"))["cache"] == "stream"
    # the streamed webdataset run shuffles shards and a buffer: another order, so other weights
    wds_stream = fit(_cfg(shards, tmp_path / "ws", format="wds", cache="stream"), progress=False)
    assert any(not torch.equal(a, b) for a, b in zip(_weights(wds_stream).values(), _weights(memory).values()))


def test_memory_run_resumes_bitwise_and_keeps_its_cache(shards, tmp_path):
    kw = dict(cache="memory", checkpoint_every=5, epochs=2)  # 6 steps per epoch
    a = fit(_cfg(shards, tmp_path / "a", **kw), progress=False)
    cfg_b = _cfg(shards, tmp_path / "b", **kw)
    with pytest.raises(TrainingStopped):
        fit(cfg_b, progress=False, stop_after_step=8)
    with pytest.raises(RispError, match="--cache memory"):  # another sample order cannot continue this run
        fit(_cfg(shards, tmp_path / "b", **dict(kw, cache="stream")), resume=True, progress=False)
    b = fit(_cfg(shards, tmp_path / "b", **dict(kw, cache="auto")), resume=True, progress=False)  # auto: the run's own
    _assert_same_weights(a, b)


def test_resuming_with_other_counts_is_said_or_refused(shards, tmp_path, capsys):
    """Another --threads continues a run with a note; another --workers matters only where it changes the sample
    order — streamed webdataset shards, 1 → 2 effective workers (refused before anything is written) — and not
    from memory or the zarr stream; another process count is refused."""
    import risp_train.train as train_mod

    kw = dict(cache="memory", checkpoint_every=5, epochs=1)
    with pytest.raises(TrainingStopped):
        fit(_cfg(shards, tmp_path / "m", **kw), progress=False, stop_after_step=5)
    capsys.readouterr()
    fit(_cfg(shards, tmp_path / "m", **dict(kw, threads=2, workers=1)), resume=True, progress=False)
    err = capsys.readouterr().err
    assert "note: resuming with torch threads 1→2" in err
    for fmt, refused in (("wds", True), ("zarr", False)):  # 48 samples in 3 shards
        kw = dict(cache="stream", format=fmt, checkpoint_every=5, epochs=1)
        run = tmp_path / f"s-{fmt}"
        with pytest.raises(TrainingStopped):
            fit(_cfg(shards, run, **kw), progress=False, stop_after_step=5)
        before = sorted(p.name for p in run.iterdir())
        if refused:
            with pytest.raises(RispError, match="pass --workers 0"):
                fit(_cfg(shards, run, **dict(kw, workers=2)), resume=True, progress=False)
            assert sorted(p.name for p in run.iterdir()) == before
            fit(_cfg(shards, run, **dict(kw, workers=1)), resume=True, progress=False)  # 0 and 1: one reader
        else:
            fit(_cfg(shards, run, **dict(kw, workers=2)), resume=True, progress=False)
    state = {"world_size": 2, "threads": 1, "workers": 0}
    with pytest.raises(RispError, match="trained with 2"):
        train_mod.check_resume_counts(state, open_shards(shards["train"]), "memory", 1, 1, 0, "last.pt", quiet=True)


def test_auto_streams_when_memory_is_short_and_memory_refuses_clearly(shards):
    s = open_shards(shards["train"])
    need = estimate_bytes(s, True)
    assert resolve_cache("auto", s, True, available=4 * need) == "memory"
    assert resolve_cache("auto", s, True, available=need) == "stream"  # more than half of what is free
    assert resolve_cache("stream", s, True, available=10 * need) == "stream"
    # two torchrun processes on one machine each hold the whole set: each may count on half the memory
    assert resolve_cache("auto", s, True, available=4 * need, processes=2) == "memory"
    assert resolve_cache("auto", s, True, available=4 * need, processes=3) == "stream"
    with pytest.raises(RispError, match="for each of 3 processes"):
        resolve_cache("memory", s, True, available=2 * need, processes=3)
    with pytest.raises(RispError, match="--cache stream"):
        resolve_cache("memory", s, True, available=need // 2)
    with pytest.raises(RispError, match="unknown --cache"):
        resolve_cache("disk", s, True)
    with pytest.raises(RispError, match="unknown --cache"):
        make_config(shards["train"], "x", preset="cpu", cache="disk")


def test_memory_fit_keeps_the_thread_default_and_honours_threads(shards, tmp_path, monkeypatch):
    """From memory the default thread count is the streamed path's (CPUs − workers: one torch thread on a shared
    2-core machine, where a second one spins against other work), and --threads N is taken as given."""
    import risp_data.threads as threads_mod

    monkeypatch.setattr(threads_mod, "available_cpus", lambda: 2)
    default = fit(_cfg(shards, tmp_path / "m", cache="memory", workers=1, epochs=1, threads=0), progress=False)
    two = fit(_cfg(shards, tmp_path / "t", cache="memory", workers=1, epochs=1, threads=2), progress=False)
    assert torch.load(default, weights_only=True)["threads"] == 1
    assert torch.load(two, weights_only=True)["threads"] == 2
    assert json.load(open(tmp_path / "t" / "config.json"))["threads"] == 2


def _damaged_copy(shards, tmp_path, shard: int):
    """A copy of the training shards whose shard ``shard`` has 64 zeroed bytes inside an image (its sha256 fails)."""
    import tarfile

    folder = tmp_path / "damaged"
    shutil.copytree(shards["train"], folder)
    tar = sorted((folder / "wds").glob("*.tar"))[shard]
    with tarfile.open(tar) as t:
        member = next(m for m in t.getmembers() if m.name.endswith("image.exr"))
    data = bytearray(tar.read_bytes())
    data[member.offset_data + 100:member.offset_data + 164] = bytes(64)
    tar.write_bytes(bytes(data))
    return folder


def test_damaged_shard_is_one_error_before_training(shards, tmp_path):
    folder = _damaged_copy(shards, tmp_path, 1)
    out = tmp_path / "run"
    out.mkdir()
    (out / "model.pt").write_bytes(b"an earlier model")  # --overwrite must not remove it before the data is read
    with pytest.raises(RispError) as e:
        fit(make_config(str(folder), str(out), preset="cpu", epochs=1, batch_size=8, width=4, workers=0,
                        format="wds", cache="memory", stats_samples=8), progress=False, overwrite=True)
    assert "\n" not in str(e.value) and "sha256" in str(e.value) and "shard" in str(e.value), e.value
    assert sorted(p.name for p in out.iterdir()) == ["model.pt"]  # nothing written, nothing lost
    assert (out / "model.pt").read_bytes() == b"an earlier model"


@pytest.mark.parametrize("where", ["val", "stream"])
def test_overwrite_keeps_the_old_run_when_the_data_is_bad(shards, tmp_path, where):
    """--overwrite deletes the old run only after the data has been read: a damaged --val folder (read for the
    untrained network's held-out error) or a damaged first shard read for the normalisation statistics while
    streaming is one error line, and the old model.pt and last.pt stay."""
    folder = _damaged_copy(shards, tmp_path, 0)
    out = tmp_path / "run"
    out.mkdir()
    for name in ("model.pt", "last.pt"):
        (out / name).write_bytes(b"an earlier run")
    train, extra = (shards["train"], dict(val=str(folder), cache="memory")) if where == "val" else \
        (str(folder), dict(cache="stream"))
    with pytest.raises(RispError) as e:
        fit(make_config(train, str(out), preset="cpu", epochs=1, batch_size=8, width=4, workers=0, format="wds",
                        stats_samples=8, **extra), progress=False, overwrite=True)
    assert "\n" not in str(e.value) and "sha256" in str(e.value), e.value
    assert sorted(p.name for p in out.iterdir()) == ["last.pt", "model.pt"]
    assert all((out / n).read_bytes() == b"an earlier run" for n in ("model.pt", "last.pt"))


def test_resuming_from_a_final_model_is_one_error_line(shards, tmp_path):
    """A model.pt copied to last.pt holds weights but no optimiser state: --resume says so instead of a KeyError."""
    out = tmp_path / "run"
    cfg = make_config(shards["train"], str(out), preset="cpu", epochs=1, batch_size=8, width=4, workers=0,
                      format="wds", cache="memory", stats_samples=8)
    fit(cfg, progress=False)
    shutil.copy(out / "model.pt", out / "last.pt")
    with pytest.raises(RispError, match=r"last.pt: not a resumable checkpoint \(no optimizer, scheduler"):
        fit(cfg, resume=True, progress=False)


def test_cli_unknown_cache_is_one_error_line(shards, tmp_path):
    from click.testing import CliRunner

    from risp_train.cli import cli

    out = tmp_path / "run"
    r = CliRunner().invoke(cli, ["fit", shards["train"], "--out", str(out), "--cache", "disk", "--quiet"])
    assert r.exit_code != 0 and "unknown --cache 'disk'" in r.output and r.output.strip().count("\n") == 0, r.output
    assert not out.exists()


@pytest.mark.parametrize("field", ["image", "state", "jacobian", "psi"])
def test_a_non_finite_value_in_any_stored_array_is_one_error(field):
    """collate (both the streaming loader's and the in-memory decode's) refuses NaN/inf in every array a sample
    holds; ψ, recorded with each batch, passed unchecked."""
    from risp_train.data import collate

    def sample(key):
        return {"key": key, "url": "shard-000000.tar", "image": np.zeros((4, 4, 3), np.float32),
                "state": np.zeros(3), "psi": np.ones(5), "jacobian": np.zeros((5, 4, 4, 3), np.float32)}

    good, bad = sample("s0"), sample("s1")
    collate([good, sample("s2")], state_dim=3)
    bad[field] = bad[field].copy()
    bad[field].flat[0] = np.nan
    with pytest.raises(RispError, match=f"sample s1 in shard-000000.tar: {field} contains NaN or inf"):
        collate([good, bad], state_dim=3)


def test_collate_checks_every_sample_against_the_manifests_shapes():
    """An 8×8 sample among 16×16 ones was blamed on its neighbour (the batch's first image was the reference), and
    a manifest that misstated the resolution or the ψ count trained a model recording the wrong one."""
    import numpy as np
    import pytest

    from risp_data.errors import RispError
    from risp_train.data import collate

    def sample(key, res=16, k=8):
        return {"key": key, "url": "shard-000000.tar", "image": np.zeros((res, res, 3), np.float32),
                "state": np.zeros(6), "psi": np.zeros(k), "jacobian": np.zeros((k, res, res, 3), np.float32)}

    assert collate([sample("s0"), sample("s1")], 6, 16, 8)["image"].shape == (2, 16, 16, 3)
    with pytest.raises(RispError, match=r"sample s0 in shard-000000.tar: image has shape \(8, 8, 3\), but the "
                                        r"manifest says 16×16 pixels"):
        collate([sample("s0", res=8), sample("s1")], 6, 16, 8)
    with pytest.raises(RispError, match=r"sample s1 .*: psi has shape \(7,\), but the manifest names 8"):
        collate([sample("s0"), sample("s1", k=7)], 6, 16, 8)
