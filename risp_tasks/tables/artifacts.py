"""Data sets, networks and reference videos of a table, made through the public functions and reused by the
checksum of their configuration.

    <cache>/data/<env>-train-<key>/       risp_data.generate.run_job (train domain, with Jacobians)
    <cache>/data/<env>-test-r<k>-<key>/   target-domain test images of repeat k (no Jacobians)
    <cache>/runs/<env>-<reg>-<key>/       risp_train.train.fit (key: training config + data manifest hash)
    <cache>/videos/<env>-r<k>-<key>.mp4   risp_tasks.tasks.reference.make_reference (target domain, random look;
                                          the key includes the motion's revision, MOTION_REVISIONS)

``<key>`` is the first 12 hex digits of the sha256 of the JSON of everything that determines the artifact (the
environment's look, risp_data.envs.look, included), so a changed setting or appearance makes a new artifact and
an unchanged one is found again (also by another table).  Both
run_job and fit resume a half-made artifact.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, replace

from risp_data.errors import RispError

from .config import TableConfig, repeat_seed

#: Seeds of the test sets and reference videos: repeat k uses TEST_SEED + repeat_seed(seed, k), never the training seed.
TEST_SEED = 1000


def checksum(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:12]


def look_key(settings, env: str, skip: tuple[str, ...]) -> str:
    """Checksum of a rendering job's settings (a dataclass, less ``skip``) and of the environment's look: data of
    an environment whose appearance risp has since changed is not found again (risp_data.envs.look)."""
    from risp_data.envs.look import look_fingerprint

    return checksum({**{k: v for k, v in asdict(settings).items() if k not in skip}, "look": look_fingerprint(env)})


def _quiet(*_):
    return None


def _complete(folder: str) -> bool:
    """Whether a render folder is finished (its manifest's ``complete``, kept by run_job, which checks the files)."""
    from risp_data.errors import RispError
    from risp_data.shards.manifest import load_manifest

    try:
        return bool(load_manifest(folder).get("complete"))
    except RispError:  # absent or unreadable: run_job makes or repairs it
        return False


class Artifacts:
    """Lazily made, cached artifacts of one table configuration (one environment at a time)."""

    def __init__(self, cfg: TableConfig, cache: str | None = None):
        self.cfg = cfg
        self.root = cache or cfg.out

    # ------------------------------------------------------------------ data sets

    def _render(self, env: str, name: str, n: int, domain: str, seed: int, jacobian: bool) -> str:
        from risp_data.generate import RenderJob, run_job

        cfg = self.cfg
        job = RenderJob(env=env, n=n, out="", domain=domain, formats=("wds",), resolution=cfg.resolution,
                        spp=cfg.spp, seed=seed, workers=1, shard_size=min(64, n), jacobian=jacobian)
        key = look_key(job, env, skip=("out", "workers"))
        out = os.path.join(self.root, "data", f"{env}-{name}-{key}")
        if not _complete(out):  # a finished set is only read (cells in parallel processes must not lock it)
            run_job(replace(job, out=out), progress=cfg.progress, log=_quiet)
        return out

    def train_shards(self, env: str) -> str:
        return self._render(env, "train", self.cfg.n_train, "train", self.cfg.seed, True)

    def test_shards(self, env: str, repeat: int) -> str:
        return self._render(env, f"test-r{repeat}", self.cfg.n_test, "target", TEST_SEED + repeat_seed(self.cfg.seed, repeat), False)

    # ------------------------------------------------------------------ networks

    def network(self, env: str, which: str, seed: int | None = None) -> str:
        """Checkpoint of the network ``which`` ("none": ours-no-grad; "reg": ours with cfg.reg; or a regularizer's
        name) trained with ``seed`` (default: the table's seed) on the environment's training set."""
        from risp_train.data import manifest_hash, open_shards
        from risp_train.train import MODEL, fit

        shards = self.train_shards(env)
        tcfg = train_config(self.cfg, which, seed, shards)
        out = os.path.join(self.root, "runs", f"{env}-{tcfg.reg}-{network_key(tcfg, env, manifest_hash(open_shards(shards).manifest))}")
        model = os.path.join(out, MODEL)
        if not os.path.exists(model):
            fit(replace(tcfg, out=out), resume=True, progress=self.cfg.progress)
        return model

    # ------------------------------------------------------------------ reference videos

    def video_config(self, env: str, repeat: int, frames: int | None = None):
        """(ReferenceConfig, cached video path) of repeat ``repeat``'s reference video: the path's key is the
        checksum of the settings, the look and, for a revised motion, the motion's revision."""
        from risp_tasks.tasks.reference import MOTION_REVISIONS, ReferenceConfig

        cfg = self.cfg
        ref = ReferenceConfig(env=env, out="", frames=frames or cfg.frames, fps=10.0, resolution=cfg.resolution, spp=cfg.spp,
                              domain="target", seed=TEST_SEED + repeat_seed(cfg.seed, repeat), progress=False)
        key = look_key(ref, env, skip=("out", "progress", "overwrite"))
        if env in MOTION_REVISIONS:  # a revised motion is a new video (unrevised motions keep their keys)
            key = checksum({"video": key, "motion": MOTION_REVISIONS[env]})
        return ref, os.path.join(self.root, "videos", f"{env}-r{repeat}-{key}.mp4")

    def video(self, env: str, repeat: int, frames: int | None = None) -> dict:
        """The target-domain reference video of repeat ``repeat``: {"video", "truth", "actions"} paths."""
        from risp_tasks.tasks.reference import actions_path, make_reference, truth_path

        ref, out = self.video_config(env, repeat, frames)
        if not (os.path.exists(out) and os.path.exists(truth_path(out))):  # the truth is written last
            make_reference(replace(ref, out=out, overwrite=True))  # a video whose truth was not written is redone
        actions = actions_path(out)
        return {"video": out, "truth": truth_path(out), "actions": actions if os.path.exists(actions) else None}


def train_config(cfg: TableConfig, which: str, seed: int | None = None, shards: str = ""):
    """The risp-train configuration of the table's network ``which`` (see Artifacts.network)."""
    from risp_train.config import make_config

    reg = cfg.reg if which == "reg" else which
    # --quick trains a few steps: a late start (quadrotor, cube: half the run) would leave its `ours` the network of
    # `ours-no-grad`, so the smoke run would never reach the regularizer; it ramps in from the first step there
    # (`none` records the same start: the regularizer table times every row over the same epochs)
    gamma_start = 0.0 if cfg.quick else None
    return make_config(shards, "", preset=cfg.train_preset, reg=reg, epochs=cfg.epochs, width=cfg.width,
                       batch_size=cfg.batch_size, seed=cfg.seed if seed is None else seed, workers=cfg.workers,
                       cache="memory", threads=1,  # one thread, as every cell (grid.py); memory: a fixed order
                       gamma_start=gamma_start)


def network_identity(cfg: TableConfig, env: str, which: str, seed: int | None = None) -> str:
    """network_key less the data: what a cell records of the network it read (grid.cell_networks).  The data's own
    settings are in the table's folder key and the look in the cell's; a new risp-train default (preset values,
    γ, the stem rule) changes this, so cells made with the old network are computed again."""
    return network_key(train_config(cfg, which, seed), env, "")


def network_key(tcfg, env: str, data_hash: str) -> str:
    """Checksum of what makes a network: its training configuration, the γ schedule it trains with (resolved: a
    new per-environment default in GAMMA_DEFAULTS or GAMMA_START_DEFAULTS is a new network), the rule that picks
    the automatic stem (a new rule is a new architecture) and its data (manifest hash)."""
    from risp_train.config import resolved_gamma, resolved_gamma_start
    from risp_train.model import MIN_LAST_MAP, STEM_FACTOR

    # not what makes a network: where it is written, how it is computed, and --rank-check (torchrun only: a resync
    # makes rank 0's network, which a single process is anyway)
    ident = {k: v for k, v in tcfg.to_dict().items()
             if k not in ("shards", "out", "workers", "threads", "device", "rank_check")}
    if tcfg.stem == "auto":
        ident["stem_rule"] = {"min_last_map": MIN_LAST_MAP, "factors": STEM_FACTOR}
    return checksum({**ident, "gamma": resolved_gamma(tcfg, env), "gamma_start": resolved_gamma_start(tcfg, env),
                     "data": data_hash})


def prepare(cfg: TableConfig, env: str, cache: str | None = None) -> None:
    """Make every artifact the table's cells of ``env`` read, so that concurrent cells (Ray) only read them."""
    from .methods import estimation_network, get_method

    art = Artifacts(cfg, cache)
    if cfg.table == "sampling":
        from .sampling import landscape

        if env != "rod":  # the landscapes are the rod's whatever --envs says: one task makes them, not one per env
            return

        for r in range(cfg.repeats):
            landscape(cfg, art, r)
        return
    if cfg.table == "regularizers":
        for r in range(cfg.repeats):
            art.test_shards(env, r)
            for reg in cfg.methods:
                _loadable(art.network(env, reg, seed=repeat_seed(cfg.seed, r)))
        return
    read = estimation_network if cfg.table == "estimation" else (lambda m: get_method(m).network)
    networks = {read(m) for m in cfg.methods} - {None}
    if cfg.table == "estimation":
        for r in range(cfg.repeats):
            art.test_shards(env, r)
        if {"average", "pixelwise", "perceptual"} & set(cfg.methods):
            art.train_shards(env)
    else:
        if cfg.table in ("imitation", "control") and env == "cube":  # no actions: its cells are N/A, read nothing
            return
        if any(get_method(m).network is None for m in cfg.methods):
            networks.add("reg")  # rows without a network read the initial state from `ours`'
        for r in range(cfg.repeats):
            art.video(env, r)
    for which in sorted(networks):
        _loadable(art.network(env, which))


def _loadable(model: str) -> None:
    """A cached network that cannot be loaded (a damaged file) ends the run here with one line, rather than failing
    every cell that reads it, on every run."""
    from risp_train.predictor import load

    try:
        load(model)
    except RispError as e:
        raise RispError(f"{e} (a cached network of the table: delete {os.path.dirname(model)} to train it again)") from None
