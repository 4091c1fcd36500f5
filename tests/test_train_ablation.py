"""risp-train ablation on a tiny scale: pooled rendering configurations, trainings, evaluation, figure."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from risp_train.cli import cli


@pytest.mark.slow
def test_ablation_tiny(tmp_path):
    out = tmp_path / "abl"
    args = ["ablation", "--env", "cube", "--out", str(out), "--pools", "2,per-sample", "--regs", "none,stochastic",
            "--n-train", "16", "--n-eval", "8", "--res", "16", "--spp", "2", "--shard-size", "8", "--epochs", "1",
            "--batch-size", "8", "--width", "4", "--workers", "0", "--quiet"]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    summary = json.load(open(out / "ablation.json"))
    rows = {(x["pool"], x["reg"]) for x in summary["results"]}
    assert rows == {("2", "none"), ("2", "stochastic"), ("per-sample", "none"), ("per-sample", "stochastic")}
    for x in summary["results"]:
        for s in ("unseen", "target"):
            assert np.isfinite(x[s]["mean"]) and x[s]["std"] > 0
    assert (out / "ablation.png").stat().st_size > 0 and "| 2 | stochastic |" in open(out / "ablation.md").read()
    # the pooled training set really uses only two rendering configurations, alternating
    from risp_data.shards import iter_wds, load_manifest

    m = load_manifest(str(out / "shards" / "train-pool-2"))
    assert m["psi_pool"]["size"] == 2
    pooled = list(iter_wds(str(out / "shards" / "train-pool-2")))
    psis = [s["psi"] for s in pooled]
    assert len({tuple(p) for p in psis}) == 2 and np.array_equal(psis[0], psis[2])
    # the pooled samples come from risp-data's own sample renderer: its metadata (variant, integrator), plus the pool
    assert [s["meta"]["psi_pool_index"] for s in pooled[:4]] == [0, 1, 0, 1]
    assert all(s["meta"]["variant"] and s["meta"]["integrator"] for s in pooled)
    per_sample = [s["psi"] for s in iter_wds(str(out / "shards" / "train-pool-per-sample"))]
    assert len({tuple(p) for p in per_sample}) == 16
    # run again: everything is reused (no re-render, no re-training), same numbers
    r2 = CliRunner().invoke(cli, args)
    assert r2.exit_code == 0, r2.output
    assert json.load(open(out / "ablation.json"))["results"] == summary["results"]
    assert "with 2 rendering configurations or a new rendering configuration per sample" in open(out / "ablation.md").read()
    # run again with another training option: the finished runs are not passed off as the new ones
    before = (out / "ablation.json").read_bytes()
    r3 = CliRunner().invoke(cli, [a if a != "1" else "2" for a in args])  # --epochs 2
    assert r3.exit_code == 1 and "was trained with other options than this ablation asks for (epochs=1→2)" in r3.output
    assert (out / "ablation.json").read_bytes() == before
    for extra, words in ((["--pools", ""], "--pools is empty"), (["--regs", "none,none"], "--regs names an entry twice"),
                         (["--gamma", "-1"], "--gamma must be a finite number >= 0"),
                         (["--batch-size", "100"], "--batch-size 100 is larger than --n-train 16")):
        bad = CliRunner().invoke(cli, args[:4] + [str(tmp_path / "y")] + args[5:] + extra)
        assert bad.exit_code == 1 and words in bad.output, bad.output
        assert not os.path.exists(tmp_path / "y")  # refused before anything is rendered
    bad = CliRunner().invoke(cli, ["ablation", "--env", "cube", "--out", str(tmp_path / "x"), "--pools", "0"])
    assert bad.exit_code != 0 and "--pools" in bad.output
    assert not os.path.exists(tmp_path / "x" / "ablation.json")


def test_a_pooled_folder_is_verified_with_its_looks_and_resumed_only_by_the_ablation(tmp_path):
    """A pooled set (sample i rendered with pool[i mod P]): risp-data verify re-renders each sample with its pool
    look (it reported every sample as not the one its seed gives), and risp-data render / verify --repair refuse
    to re-render its shards (they gave the missing samples looks of their own under the pool's manifest); the
    ablation's own render resumes it with the pool."""
    from risp_data.cli import cli as data_cli
    from risp_data.generate import RenderJob
    from risp_data.shards import iter_wds
    from risp_train.ablation import config_pool, render_pooled

    out = str(tmp_path / "pooled")
    job = RenderJob(env="cube", n=4, out=out, domain="train", formats=("wds",), resolution=16, spp=2, seed=0,
                    workers=1, shard_size=2, jacobian=True)
    pool = config_pool("cube", 1, 0)
    render_pooled(job, pool, progress=False)
    r = CliRunner().invoke(data_cli, ["verify", out, "--samples", "4"])
    assert r.exit_code == 0, r.output
    shard = os.path.join(out, "wds", sorted(os.listdir(os.path.join(out, "wds")))[1])
    os.remove(shard)
    for args in (["verify", out, "--samples", "2", "--repair"],
                 ["render", "--env", "cube", "--n", "4", "--out", out, "--res", "16", "--spp", "2", "--seed", "0",
                  "--shard-size", "2", "--format", "wds", "--quiet"]):
        r = CliRunner().invoke(data_cli, args)
        assert r.exit_code == 1 and "rendered by risp-train ablation with a pool of 1 look(s)" in r.output, r.output
        assert not os.path.exists(shard)
    render_pooled(job, pool, progress=False)  # the ablation resumes it: every sample with the pool's one look
    psis = {tuple(s["psi"]) for s in iter_wds(out)}
    assert psis == {tuple(np.asarray(pool[0].psi).tolist())}
    other = config_pool("cube", 1, 5)
    with pytest.raises(Exception, match="another pool of looks"):
        render_pooled(job, other, progress=False)


def test_a_pooled_render_killed_at_its_first_shard_resumes(tmp_path, monkeypatch):
    """The pool is in the manifest on disk before the first shard is written: a kill between a shard's marker
    and the manifest update leaves a folder the same pool resumes (it was refused as 'another pool')."""
    import risp_data.shards.writer as writer
    from risp_data.generate import RenderJob
    from risp_data.shards import iter_wds, load_manifest
    from risp_train.ablation import config_pool, pool_record, render_pooled

    out = str(tmp_path / "pooled")
    job = RenderJob(env="cube", n=4, out=out, domain="train", formats=("wds",), resolution=16, spp=2, seed=0,
                    workers=1, shard_size=2, jacobian=True)
    pool = config_pool("cube", 2, 0)
    real = writer.write_shard

    def killed_after_the_marker(*a, **k):
        real(*a, **k)
        raise KeyboardInterrupt  # the marker is written, the manifest not yet updated

    monkeypatch.setattr(writer, "write_shard", killed_after_the_marker)
    with pytest.raises(KeyboardInterrupt):
        render_pooled(job, pool, progress=False)
    assert load_manifest(out)["psi_pool"] == pool_record(pool)
    monkeypatch.setattr(writer, "write_shard", real)
    render_pooled(job, pool, progress=False)
    assert [s["meta"]["psi_pool_index"] for s in iter_wds(out)] == [0, 1, 0, 1]


def test_the_pooled_render_sets_its_thread_counts_and_gives_them_back(tmp_path, monkeypatch):
    """As risp-data's in-process render: Dr.Jit on the CPUs the process may use (here made 1), not its default of
    every core of the machine, and one torch thread while rendering; the caller's counts come back afterwards."""
    import drjit as dr
    import torch

    import risp_data.generate as gen
    import risp_data.threads as threads
    from risp_data.generate import RenderJob
    from risp_train.ablation import config_pool, render_pooled

    monkeypatch.setattr(threads, "available_cpus", lambda: 1)
    before = dr.thread_count(), torch.get_num_threads()
    seen = []
    real = gen.render_sample
    monkeypatch.setattr(gen, "render_sample", lambda *a, **k: (seen.append((dr.thread_count(),
                                                                             torch.get_num_threads())),
                                                               real(*a, **k))[1])
    torch.set_num_threads(2)
    dr.set_thread_count(2)
    try:
        job = RenderJob(env="cube", n=2, out=str(tmp_path / "p"), domain="train", formats=("wds",), resolution=8,
                        spp=1, seed=0, workers=1, shard_size=2, jacobian=True)
        render_pooled(job, config_pool("cube", 1, 0), progress=False)
        assert len(seen) == 2 and all(s == (1, 1) for s in seen), seen
        assert dr.thread_count() == 2 and torch.get_num_threads() == 2
    finally:
        dr.set_thread_count(before[0])
        torch.set_num_threads(before[1])
