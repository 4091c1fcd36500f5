"""One readable training loop (``risp-train fit``).

    cfg = make_config("shards/cube", "runs/cube", preset="cpu", reg="stochastic")
    fit(cfg)                      # → runs/cube/model.pt, last.pt, losses.csv, losses.png, config.json

Per step (docs/training.md): raw images I (B,H,W,3) and stored J (B,K,H,W,3) → normalized input x and
tangents ∂x/∂ψ (chain rule of the input normalization) → L = mean ℓ + γ(t) mean r (regularizers.py) →
backward → gradients averaged over ranks → Adam step → cosine learning-rate step.

Randomness is explicit: the initial weights come from ``seed``; the data order of epoch e from
(seed, e) (data.py); the stochastic regularizer's v at global step t on rank r from a torch.Generator
seeded with SeedSequence(seed, r, t).  The run's position is therefore (epoch, batch, global step), and
a resumed run (``--resume``) replays exactly the same computation.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import json
import os
import re
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch

from risp_data.errors import RispError

from . import checkpoint as ckpt_io
from .config import RESUME_FIELDS, TrainConfig, resolved_gamma, resolved_gamma_start
from .data import (ShardSet, check_complete, check_environment, iter_batches, make_loader, manifest_hash,
                   map_style_steps, open_shards, sample_counts, steps_per_epoch)
from .checkpoint import SET_ASIDE
from .memory import load_memory_set, memory_batches, resolve_cache
from .model import ModelConfig, ResNet18, build_model, min_resolution, stem_for_resolution
from .normalization import Normalization, StatsAccumulator
from .regularizers import gamma_at, psi_scale, risp_loss
from risp_data.atomic import (LOCK_FILE, TEMP_PREFIX, atomic_write, check_writable, folder_lock, remove_temporaries,
                              write_text_atomic)
from risp_data.shards.manifest import package_versions, risp_commit
from risp_data.threads import set_torch_threads

LAST = "last.pt"  # the resumable checkpoint, rewritten at each epoch end (and every N steps)
MODEL = "model.pt"  # the final checkpoint (same format), written when training completes
CSV_FIELDS = ("step", "epoch", "batch", "lr", "gamma", "loss", "error", "reg", "seconds")


class TrainingStopped(Exception):
    """Raised by ``fit(stop_after_step=...)``: a stand-in for a kill, used by the resume tests."""


@dataclass(frozen=True)
class Dist:
    rank: int = 0
    world_size: int = 1


def init_distributed() -> Dist:
    """Join the torchrun process group (gloo, CPU) when WORLD_SIZE > 1; otherwise a single process.

    A group this creates is destroyed at exit (``atexit``: before the interpreter is torn down; left to the
    teardown, gloo's threads can abort the process, "terminate called without an active exception",
    pytorch/pytorch#190489). It is not destroyed when ``fit`` returns: a second ``fit`` in the process reuses it
    (creating a group again on the same store can hang, pytorch/pytorch#114585)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist()
    import torch.distributed as dist

    if not dist.is_initialized():  # a caller's own group (e.g. a FileStore in tests) stays the caller's
        dist.init_process_group("gloo")
        import atexit

        atexit.register(_destroy_group)
    return Dist(dist.get_rank(), dist.get_world_size())


def _destroy_group() -> None:
    """The exit handler of a group ``init_distributed`` created (local for gloo: no rank waits for another)."""
    import torch.distributed as dist

    if dist.is_initialized():
        dist.destroy_process_group()


def agreed_cache(cache: str) -> str:
    """``memory`` when every rank chose it, else ``stream`` (one all-reduce of 1/0 with MIN)."""
    import torch.distributed as dist

    flag = torch.tensor([1 if cache == "memory" else 0])
    dist.all_reduce(flag, op=dist.ReduceOp.MIN)
    return "memory" if int(flag) == 1 else "stream"


def allreduce_gradients(params: list[torch.nn.Parameter], world_size: int) -> None:
    """Average gradients over ranks (one flat all-reduce; parameters without a gradient count as 0)."""
    import torch.distributed as dist

    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat)
    flat /= world_size
    offset = 0
    for p in params:
        n = p.numel()
        p.grad = flat[offset:offset + n].view_as(p).clone()
        offset += n


def weights_digest(state: dict) -> str:
    """sha256 over a state_dict (names, dtypes, shapes and bytes, in order): equal weights, equal digest."""
    h = hashlib.sha256()
    for name, t in state.items():
        t = t.detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())  # raw bytes: any dtype, bfloat16 included
    return h.hexdigest()


def rank_digests(net: torch.nn.Module, world_size: int) -> list[str]:
    """Every rank's weights digest, in rank order (one all_gather_object; a single process gives its own)."""
    mine = weights_digest(net.state_dict())
    if world_size <= 1:
        return [mine]
    import torch.distributed as dist

    out: list = [None] * world_size
    dist.all_gather_object(out, mine)
    return [str(d) for d in out]


def check_ranks_agree(digests: list[str], epoch: int) -> None:
    """The ranks train one network: after the all-reduced steps their weights must be bit-equal (docs/training.md).

    Every rank sees the same gathered list, so every rank raises together (no rank left waiting in a collective).
    """
    if len(set(digests)) > 1:
        groups = ", ".join(f"rank {r}: {d[:12]}" for r, d in enumerate(digests))
        raise RispError(f"the {len(digests)} torchrun ranks' weights differ after epoch {epoch} ({groups}); "
                        "they no longer train one network (mixed torch versions or devices across ranks?); "
                        "--rank-check resync gives every rank rank 0's weights at each epoch end instead")


def broadcast_rank0_state(net: torch.nn.Module, opt: torch.optim.Optimizer) -> None:
    """Every rank takes rank 0's weights, buffers and optimizer state (one ``broadcast_object_list``).

    For ranks that drift apart by round-off (e.g. machines whose CPUs take other kernel paths): after it the ranks
    train one network again, rank 0's, which is the one the checkpoints hold.
    """
    import torch.distributed as dist
    from torch.utils._pytree import tree_map_only

    # CPU copies: a pickled CUDA tensor names its device, which another node may not have (load_state_dict moves
    # the weights to each parameter's device, Adam its state to its parameter's)
    mine = {"model": net.state_dict(), "optimizer": opt.state_dict()} if dist.get_rank() == 0 else None
    box = [tree_map_only(torch.Tensor, lambda t: t.detach().cpu(), mine) if mine is not None else None]
    dist.broadcast_object_list(box, src=0)
    if dist.get_rank() != 0:
        net.load_state_dict(box[0]["model"])
        opt.load_state_dict(box[0]["optimizer"])


def agreed_weights(net: torch.nn.Module, opt: torch.optim.Optimizer, world_size: int, epoch: int, mode: str,
                   resyncs: list, echo=None) -> list[str]:
    """The ranks' digests at an epoch end, checked equal (``mode`` ``stop``), or first made equal from rank 0's
    state when they differ (``resync``; the event is appended to ``resyncs`` and echoed by rank 0)."""
    digests = rank_digests(net, world_size)
    if mode == "resync" and len(set(digests)) > 1:
        broadcast_rank0_state(net, opt)
        resyncs.append({"epoch": epoch, "rank_weights_sha256": digests})
        import torch.distributed as dist

        if echo is not None and dist.get_rank() == 0:
            echo(f"note: the {world_size} ranks' weights differed after epoch {epoch}; every rank now holds rank 0's "
                 "weights and optimizer state (--rank-check resync)")
        digests = rank_digests(net, world_size)
    check_ranks_agree(digests, epoch)
    return digests


def step_generator(seed: int, rank: int, step: int) -> torch.Generator:
    """The generator of the stochastic regularizer's v at (rank, global step): no hidden RNG state."""
    word = int(np.random.SeedSequence([seed, rank, step, 0xC0FFEE]).generate_state(1, dtype=np.uint64)[0])
    return torch.Generator().manual_seed(word & ((1 << 63) - 1))


def compute_normalization(shards: ShardSet, env, n: int) -> Normalization:
    """Streamed statistics over the first ``n`` samples in shard order (identical on every rank)."""
    acc = StatsAccumulator(env.target_dim)
    for batch in iter_batches(shards, 32, need_jacobian=False, state_dim=env.state_dim, limit=n):
        acc.add(batch["image"], env.state_to_target(batch["state"]))
    return acc.result()


def batch_tensors(batch: dict, norm: Normalization, env, need_tangents: bool, device: torch.device | None = None):
    """x (B,3,H,W), normalized targets (B,T) and tangents ∂x/∂ψ (B,K,3,H,W) or None, float32, on ``device``."""
    images = batch["image"].to(device)
    x = norm.images(images)
    y = norm.targets(env.state_to_target(batch["state"].to(device)).to(torch.float32))
    tangents = norm.tangents(images, batch["jacobian"].to(device)) if need_tangents else None
    return x, y, tangents


def resolve_device(name: str) -> torch.device:
    """``auto`` → the CUDA GPU when torch sees one, else the CPU; otherwise the named device, checked."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise RispError(f"unknown --device {name!r}; use auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RispError(f"--device {name}: torch sees no CUDA GPU (torch {torch.__version__}); use --device cpu")
    if device.type not in ("cpu", "cuda"):
        raise RispError(f"--device {name}: only cpu and cuda are supported")
    return device


@torch.no_grad()
def held_out_error(net: ResNet18, shards: ShardSet, norm: Normalization, env, limit: int) -> float:
    """Mean normalized-target L1 error ℓ over the first ``limit`` samples of ``shards``."""
    net.eval()
    total, n = 0.0, 0
    device = next(net.parameters()).device
    for batch in iter_batches(shards, 32, state_dim=env.state_dim, limit=limit):
        x, y, _ = batch_tensors(batch, norm, env, False, device)
        total += float((net(x) - y).abs().mean(dim=1).sum())
        n += y.shape[0]
    net.train()
    return total / max(n, 1)


def _csv_keep_until(path: str, step: int) -> None:
    """Drop log rows written after the checkpoint we resume from (a killed run may have logged more)."""
    if not os.path.exists(path):
        return
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if int(r["step"]) <= step]
    with atomic_write(path, "w", suffix=".csv") as f:
        w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        w.writeheader()
        w.writerows(rows)


def _write_json(path: str, obj) -> None:
    write_text_atomic(path, json.dumps(obj, indent=1, sort_keys=True) + "\n")


RUN_FILES = (MODEL, LAST, "config.json", "losses.csv", "losses.png", "history.json")
#: what `risp-train eval` writes into a run folder by default (risp_train.evaluate: eval-<shards>.json/.md/_scatter.png)
_EVAL_OUTPUT = re.compile(r"eval-.+(\.json|\.md|_scatter\.png)$")


def _is_run_file(name: str) -> bool:
    """A file a run folder holds: the trainer's own or an evaluation written into it."""
    return name in RUN_FILES or bool(_EVAL_OUTPUT.match(name))


def _is_bookkeeping(name: str) -> bool:
    """The lock and the temporaries (risp_data.atomic): in a run folder and a shard folder alike, so they say
    nothing about what a folder holds; remove_temporaries, not --overwrite, deletes the temporaries (a live
    writer's stay).  Also the replaced run that --overwrite keeps aside (:class:`SetAside`)."""
    return name in (LOCK_FILE, SET_ASIDE) or name.startswith(TEMP_PREFIX)


class SetAside:
    """The run that ``fit --overwrite`` replaces, kept in ``RUN/.overwritten-run`` until the new run has written its
    first checkpoint (:meth:`drop`): a fit that fails or is interrupted before that puts it back (:meth:`__exit__`,
    pushed on the fit's ExitStack), so a user's model is never lost to a fit that produced none.  A SIGKILL or a
    SIGTERM (no handler runs) leaves it aside: the next fit on the folder and ``model_file`` name it."""

    def __init__(self, out: str, echo=None):
        self.out, self.folder, self.echo = out, os.path.join(out, SET_ASIDE), echo

    @property
    def pending(self) -> bool:
        return os.path.isdir(self.folder)

    def drop(self) -> None:
        """The new run has a checkpoint: the replaced one goes.  Renamed to a temporary first (one atomic step, after
        which nothing is pending), then deleted: a deletion that fails or is interrupted half-way must not make
        ``__exit__`` restore a half-deleted old run over the new checkpoint (remove_temporaries drops the rest)."""
        if self.pending:
            import shutil

            from risp_data.atomic import temp_prefix

            doomed = os.path.join(self.out, temp_prefix() + "overwritten-run")
            os.replace(self.folder, doomed)
            shutil.rmtree(doomed, ignore_errors=True)

    def __exit__(self, kind, exc, tb) -> bool:
        if kind is not None and self.pending:
            self.restore()
        return False  # the failure itself still propagates

    def restore(self) -> None:
        """The stopped fit's own files out (its config and logs: no checkpoint), the replaced run's back."""
        for name in os.listdir(self.out):
            path = os.path.join(self.out, name)
            if _is_run_file(name) and (os.path.isfile(path) or os.path.islink(path)):
                os.unlink(path)
        for name in os.listdir(self.folder):
            os.replace(os.path.join(self.folder, name), os.path.join(self.out, name))
        os.rmdir(self.folder)
        if self.echo is not None:
            self.echo(f"note: the fit stopped before its first checkpoint: the run it was to replace is back in "
                      f"{self.out}")


def _set_aside_run(out: str, present: list[str], held: list[str]) -> None:
    """--overwrite: move the earlier run's files (RUN_FILES and the evaluations written into it) into
    ``out/.overwritten-run`` instead of deleting them (:class:`SetAside`).  One still there (check_run_folder has
    deleted a stale one) is a killed fit's: the model to keep, and the folder's run files that fit's logs (deleted)."""
    aside = os.path.join(out, SET_ASIDE)
    keep = not os.path.isdir(aside) and held  # a model or a checkpoint: a config.json alone may be anyone's
    if keep:
        os.mkdir(aside)
    for name in present:
        path = os.path.join(out, name)
        if _is_run_file(name) and (os.path.isfile(path) or os.path.islink(path)):
            if keep:
                os.replace(path, os.path.join(aside, name))
            elif os.path.isdir(aside):
                os.unlink(path)


def _run_snapshot(out: str) -> tuple:
    """(inode, mtime, size) of the run folder's model.pt and last.pt, None where absent: the state of the folder
    that --resume decides on."""
    def key(name):
        try:
            st = os.stat(os.path.join(out, name))
        except (FileNotFoundError, NotADirectoryError):  # no folder yet, or a file in its path (said later)
            return None
        return st.st_ino, st.st_mtime_ns, st.st_size

    return key(MODEL), key(LAST)


def check_run_folder(out: str, resume: bool, overwrite: bool, remove: bool = True) -> None:
    """Refuse a run folder that holds a model or checkpoint unless ``--resume`` or ``--overwrite`` says what
    to do with it; with ``--overwrite`` set every file of the earlier run aside (after every other check has passed;
    ``remove=False``: only check; :func:`_set_aside_run`): its model and checkpoint, and also its history, losses,
    config and evaluations, which would otherwise sit beside the new run's files and describe another model (a user's
    own files stay)."""
    held = [name for name in (MODEL, LAST) if os.path.exists(os.path.join(out, name))]
    if resume and overwrite:
        raise RispError("--resume and --overwrite exclude each other")
    aside = os.path.join(out, SET_ASIDE)
    if os.path.isdir(aside) and not held and not overwrite:  # a fit --overwrite killed before its first checkpoint
        raise RispError(f"{aside} holds the run that a fit --overwrite set aside before it was stopped (it wrote no "
                        f"checkpoint); move that folder's files back into {out} to keep the run, or pass --overwrite "
                        "to replace it")
    if remove and os.path.isdir(aside) and held:  # killed after its checkpoint, before it deleted the old run
        import shutil

        shutil.rmtree(aside)
    present = sorted(n for n in os.listdir(out) if not _is_bookkeeping(n)) if os.path.isdir(out) else []
    if present and not overwrite and not any(_is_run_file(name) for name in present):
        shown = ", ".join(present[:3]) + (", …" if len(present) > 3 else "")
        raise RispError(f"{out} is not empty and holds no risp-train run ({shown}); choose another --out, or "
                        "--overwrite to write the run beside those files")
    if overwrite:
        # only when the folder holds a run: its own files (RUN_FILES) and the evaluations risp-train eval wrote into
        # it — never a user's file that merely starts with "eval" (evaluate.py), nor anything in a folder of other
        # files that the run is written beside; the lock stays (a new file would lock nothing)
        if remove:
            _set_aside_run(out, present, held)
    elif held and not resume:
        raise RispError(f"{out} already holds a run ({', '.join(held)}); pass --resume to continue it, "
                        "--overwrite to replace it, or choose another --out")
    elif held == [MODEL]:  # --resume, but nothing to resume from: training anew would replace the model
        raise RispError(f"{out} holds a finished {MODEL} but no {LAST} to resume from; pass --overwrite to "
                        "train it again, or choose another --out")


def option_changes(stored_config: dict, cfg: TrainConfig, env: str, used: dict | None = None) -> list[str]:
    """``name=old→new`` for every option of RESUME_FIELDS (those that change a run) in which ``cfg`` differs from
    a stored run's config, compared as resolved: ``--gamma 0.3`` equals a run started without --gamma when the
    environment's default is 0.3.

    ``used`` is the stored run's own record of what it trained with (its checkpoint, or its ``config.json``): its
    ``gamma`` and ``gamma_start`` win over today's defaults, which may have changed since the run began (the hand's
    γ went from 0.3 to 0.05) — a resumed run must not switch to the new default half-way.  A record without
    ``gamma_start`` took its start from its own config (``--gamma-start`` was stored only there at first) and, where
    that has none either, predates the late start: its γ ramped in from the first step (0).  Without a regularizer on
    either side γ and its start change nothing and are not compared."""
    def resolved(c: TrainConfig) -> dict:
        return {**c.to_dict(), "gamma": resolved_gamma(c, env), "gamma_start": resolved_gamma_start(c, env)}

    stored, now = resolved(TrainConfig.from_dict(stored_config)), resolved(cfg)  # fields added since: defaults
    if used is not None:
        if used.get("gamma") is not None:
            stored["gamma"] = float(used["gamma"])
        start = used.get("gamma_start")  # not in the record: the run's own --gamma-start (stored only in its config
        start = stored_config.get("gamma_start") if start is None else start  # for a while), else from step 0
        stored["gamma_start"] = float(start or 0.0)
    if stored.get("reg") == "none" and now["reg"] == "none":
        stored["gamma_start"] = now["gamma_start"]
    return [f"{k}={stored.get(k)!r}→{now[k]!r}" for k in RESUME_FIELDS if stored.get(k) != now[k]]


def val_record(val, cfg: TrainConfig) -> dict | None:
    """What a run's held-out curve is measured on: the --val shards' manifest hash and the samples taken from them
    (None without --val).  Stored in the checkpoint, so that a resumed run's ``val_error`` column stays one curve."""
    if val is None:
        return None
    return {"manifest_hash": manifest_hash(val.manifest), "samples": int(cfg.val_samples),
            "folder": os.path.abspath(val.folder)}


def check_resume_val(state: dict, now: dict | None, cfg: TrainConfig, path: str) -> None:
    """Refuse to resume with another held-out set than the run began with: the history's ``val_error`` would
    switch data sets half-way and the loss plot would join two curves.  Checkpoints from before the record
    (no ``val`` key) are not compared.  ``now``: this run's :func:`val_record`."""
    if "val" not in state:
        return
    was = state["val"]
    if was is None and now is None:
        return
    if was is None:
        raise RispError(f"cannot resume {path} with --val {cfg.val}: it was trained without a held-out set "
                        "(its loss history has no val_error); resume it without --val")
    if now is None:
        raise RispError(f"cannot resume {path} without --val: it was trained with --val {was.get('folder')}; "
                        "pass the same --val (its val_error curve continues on the same images)")
    if was.get("manifest_hash") != now["manifest_hash"]:
        raise RispError(f"cannot resume {path} with --val {cfg.val}: it was validated on other shards "
                        f"({was.get('folder')}; manifest hash differs); pass the same --val")
    if was.get("samples") != now["samples"]:  # val_samples: not a CLI option, but a config field of the API
        raise RispError(f"cannot resume {path} with val_samples {now['samples']}: its val_error curve was measured "
                        f"on {was.get('samples')} held-out samples")


def helper_workers(shards, cache: str, world: int, workers: int) -> int:
    """The data-worker processes that run beside each training process: streaming webdataset shards, each worker
    needs a shard of its own, so ``--workers`` beyond the shards per rank start no process (``effective_workers``)
    and must not take a CPU from the default thread count; the zarr stream and the memory set start them all."""
    from .data import effective_workers

    if cache == "stream" and shards.format == "wds":
        return effective_workers(len(shards.counts), world, workers)
    return max(0, workers)


def check_resume_counts(state: dict, shards, cache: str, world: int, threads: int, workers: int, path: str, *,
                        quiet: bool) -> None:
    """Resuming with other process, worker or thread counts than a run began with.

    Another world size (torchrun's process count) splits the samples among other ranks: refused. Streamed from
    webdataset shards, each (rank, worker) reads its own shards, so the effective worker count (capped at the
    shards per rank, 0 and 1 alike) fixes the sample order and the steps per epoch: another one is refused. The
    zarr stream and memory index samples map-style, whatever the workers. Another thread count changes the float
    sums' order: said, then continued (rounding differences that training may grow)."""
    from .data import effective_workers

    was_world = int(state.get("world_size", 1))
    if was_world != world:
        raise RispError(f"cannot resume {path} with {world} process(es): it was trained with {was_world} "
                        "(another split of the samples among the ranks); resume it with the same count")
    was_threads, was_workers = state.get("threads"), state.get("workers")
    if was_workers is not None and cache == "stream" and shards.format == "wds":
        def effective(n: int) -> int:
            return max(1, effective_workers(len(shards.counts), world, n))

        if effective(was_workers) != effective(workers):
            raise RispError(f"cannot resume {path} with --workers {workers}: it was trained streaming webdataset "
                            f"shards with --workers {was_workers} (each worker reads its own shards: another "
                            f"sample order); pass --workers {was_workers}")
    if was_threads is not None and was_threads != threads and not quiet:
        print(f"note: resuming with torch threads {was_threads}→{threads}"
              f"{' (--threads 0 follows --workers)' if was_workers != workers else ''}: the run continues, with "
              "rounding differences from an uninterrupted run (bitwise equality needs the same thread count)",
              file=sys.stderr)


def fit(cfg: TrainConfig, *, resume: bool = False, progress: bool = True,
        stop_after_step: int | None = None, overwrite: bool = False, allow_incomplete: bool = False,
        echo=None) -> str:
    """Train according to ``cfg``; returns the path of the final checkpoint (``cfg.out/model.pt``).

    Refuses an incomplete shard folder unless ``allow_incomplete`` and a folder holding a run unless
    ``resume`` or ``overwrite`` (docs/cli-train.md). The run uses one fixed torch thread count
    (``cfg.threads``; 0: the CPUs left after the data workers, risp_data.threads) and gives the caller's
    setting back when it returns.  ``echo``: called with a note line for the user (e.g. a resume of a finished
    run, which trains nothing).
    """
    device = resolve_device(cfg.device)  # before anything is written: a bad --device leaves no run folder
    dist_info = init_distributed()
    before = torch.get_num_threads()
    try:
        with contextlib.ExitStack() as hold:  # the run folder's lock, from the first write to the last
            return _fit(cfg, dist_info, device=device, resume=resume, progress=progress,
                        stop_after_step=stop_after_step, hold=hold,
                        overwrite=overwrite, allow_incomplete=allow_incomplete, echo=echo)
    finally:
        torch.set_num_threads(before)


def _fit(cfg: TrainConfig, dist_info: Dist, *, device: torch.device, resume: bool, progress: bool,
         stop_after_step: int | None, hold: contextlib.ExitStack, overwrite: bool, allow_incomplete: bool,
         echo=None) -> str:
    from risp_data.envs import get_environment

    rank, world = dist_info.rank, dist_info.world_size
    aside: SetAside | None = None  # rank 0's, once the folder is locked
    shards = open_shards(cfg.shards, cfg.format)
    env = get_environment(shards.env)
    check_environment(shards, env)
    check_complete(shards, allow_incomplete)
    need_j = cfg.reg != "none"
    if need_j and not shards.has_jacobian:
        raise RispError(f"shard folder {cfg.shards} was rendered without Jacobians; --reg {cfg.reg} needs them "
                        "(render the training set without --no-jacobian, or train without the regularizer: --reg none)")
    val = open_shards(cfg.val) if cfg.val else None
    val_rec = val_record(val, cfg)  # once: every checkpoint stores it
    if val is not None:
        if val.env != shards.env:
            raise RispError(f"--val shards {cfg.val} are of environment {val.env!r}, training shards of {shards.env!r}")
        check_environment(val, env)
        if val.resolution != shards.resolution:
            raise RispError(f"--val shards {cfg.val} are {val.resolution}×{val.resolution} images, the training "
                            f"shards {shards.resolution}×{shards.resolution}: render them at --res {shards.resolution}")
    last_path = os.path.join(cfg.out, LAST)
    seen = _run_snapshot(cfg.out)  # what the decisions below read; compared again once the folder is locked
    resuming = resume and not overwrite and os.path.exists(last_path)
    # a new network must fit the images (a resumed one keeps its checkpoint's stem, which has trained on them)
    stem = stem_for_resolution(shards.resolution) if cfg.stem == "auto" else cfg.stem
    if not resuming and shards.resolution < min_resolution(stem):
        need = min_resolution(stem)
        raise RispError(f"{cfg.shards}: {shards.resolution}×{shards.resolution} images are too small for the network "
                        f"(stem {stem!r} needs at least {need}×{need}); render them with --res {need} or more")
    gamma, gamma_start = resolved_gamma(cfg, shards.env), resolved_gamma_start(cfg, shards.env)
    # σ_ψ of the shards' own ψ distribution: the regularizer measures ψ in standard deviations (regularizers.py)
    psi_std = psi_scale(shards.env, shards.manifest.get("domain", "train"))
    mhash = manifest_hash(shards.manifest)

    # memory | stream (memory.py); a resume keeps its own below.  Every rank must choose alike (their step plans
    # differ by mode): each decides on its share of this machine's memory, then all take stream if any did.
    local_processes = int(os.environ.get("LOCAL_WORLD_SIZE", str(world)))  # torchrun's ranks on this machine
    cache = resolve_cache(cfg.cache, shards, need_j, processes=local_processes)
    if world > 1:
        cache = agreed_cache(cache)
    state = None
    if resuming:
        state = ckpt_io.load_checkpoint(last_path)
        missing = [k for k in ("config", "model_config", "optimizer", "scheduler", "progress", "normalization")
                   if k not in state]
        if missing:  # e.g. a final model.pt copied to last.pt: weights, but nothing to continue the run from
            raise RispError(f"cannot resume {last_path}: not a resumable checkpoint (no {', '.join(missing)}); a "
                            "final model.pt holds the weights only — start a new run (--overwrite)")
        # the data first: another environment or other shards is the error to report, before option differences
        ckpt_io.check_compatible(state, last_path, env=shards.env, state_names=env.state_names,
                                 resolution=shards.resolution)
        if state.get("manifest_hash") != mhash:
            raise RispError(f"cannot resume {last_path}: it was trained on other shards than {cfg.shards} "
                            "(manifest hash differs)")
        stored_cache = state.get("cache", "stream")  # checkpoints from before the cache streamed
        if cfg.cache == "auto":
            cache = stored_cache
        elif cfg.cache != stored_cache:
            raise RispError(f"cannot resume {last_path} with --cache {cfg.cache}: it was trained with --cache "
                            f"{stored_cache} (another sample order); pass --cache {stored_cache} or auto")
        changes = option_changes(state["config"], cfg, shards.env, used=state)  # before the data set is decoded below
        if changes:
            raise RispError(f"cannot resume {last_path} with different options: {', '.join(changes)}")
        check_resume_val(state, val_rec, cfg, last_path)
        final = os.path.join(cfg.out, MODEL)
        if state["progress"].get("complete") and os.path.isfile(final):
            # nothing left to train: the finished run's model.pt stays as it is (rewriting it changed its checksum,
            # which task results record)
            if echo is not None and dist_info.rank == 0:
                echo(f"note: the run in {cfg.out} is already complete ({cfg.epochs} epochs): nothing trained, "
                     f"{MODEL} unchanged")
            return final
        # a resumed run keeps the σ_ψ it began with; checkpoints from before σ_ψ followed the shards' domain
        # (2026-11-28) trained with the train domain's
        stored_psi = state.get("psi_std")
        psi_std = (torch.tensor(stored_psi, dtype=torch.float64) if stored_psi is not None
                   else psi_scale(shards.env, "train"))
    # the same default from memory, although its workers only decode before the first step: a second torch thread
    # is 1.6x faster on an idle 2-core machine but 2-3x slower than one when the cores are shared (OpenMP's
    # threads spin; docs/PERFORMANCE.md §Training data in memory): --threads 2 is the user's call
    threads = set_torch_threads(cfg.threads, workers=helper_workers(shards, cache, world, cfg.workers),
                                processes=local_processes)
    if resuming:
        check_resume_counts(state, shards, cache, world, threads, cfg.workers, last_path, quiet=rank != 0)
    if cache == "memory":
        plan = [map_style_steps(shards.num_samples, cfg.batch_size, world)] * cfg.epochs
    else:
        plan = [steps_per_epoch(shards, cfg.seed, e, cfg.batch_size, world, cfg.workers) for e in range(cfg.epochs)]
    total_steps = sum(plan)
    if total_steps == 0:
        raise RispError(f"--batch-size {cfg.batch_size} is larger than the samples each of the {world} process(es) "
                        f"and {cfg.workers} worker(s) read from {len(shards.counts)} shard(s) of {shards.folder} "
                        f"({shards.num_samples} samples); "
                        "lower --batch-size or --workers, or render more samples")

    check_run_folder(cfg.out, resume, overwrite, remove=False)  # refuse before the decode below, delete nothing
    check_writable(cfg.out, "run folder")
    mset = None
    if cache == "memory":  # decoded once (checksums and all) before anything is written; the epochs only index it
        mset = load_memory_set(shards, need_jacobian=need_j, workers=cfg.workers, state_dim=env.state_dim,
                               progress=progress and rank == 0)
    csv_path = os.path.join(cfg.out, "losses.csv")

    if state is not None:  # a resumed run continues its checkpoint's network, also one of an older automatic stem
        model_cfg = ModelConfig.from_dict(state["model_config"])
    else:
        model_cfg = ModelConfig(out_dim=env.target_dim, width=cfg.width, blocks=cfg.blocks,
                                stem=stem)
    net = build_model(model_cfg, cfg.seed).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=total_steps)
    if state is not None:
        net.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        norm = Normalization.from_dict(state["normalization"])
        epoch0, batch0, step = (int(state["progress"][k]) for k in ("epoch", "batch", "global_step"))
        history = list(state.get("history", []))
        resyncs = list(state.get("rank_resyncs") or [])
        partial_sums = state.get("epoch_sums")  # the interrupted epoch's loss sums before the checkpoint
    else:
        norm = compute_normalization(shards, env, cfg.stats_samples)
        epoch0, batch0, step, history, partial_sums = 0, 0, 0, [], None
        resyncs = []  # epoch ends at which --rank-check resync gave every rank rank 0's state
        if val is not None:  # the untrained network's held-out error, the baseline of the curve
            history.append({"epoch": -1, "step": 0, "val_error": held_out_error(net, val, norm, env, cfg.val_samples)})
    # Only now, with the data read and checked (normalisation statistics, the held-out baseline), is anything in the
    # run folder deleted or written: --overwrite on bad data loses nothing (docs/cli-train.md)
    if rank == 0:  # one process deletes: another rank's cleanup could remove rank 0's config.json temporary
        os.makedirs(cfg.out, exist_ok=True)
        # before anything is deleted: a second fit on this folder (an --overwrite, a --resume) would delete or
        # interleave the running one's files
        hold.enter_context(folder_lock(cfg.out, f"another risp-train fit is writing to {cfg.out}; wait for it "
                                                "or stop it"))
        if not overwrite and _run_snapshot(cfg.out) != seen:  # a fit that ended while this one read its data
            raise RispError(f"{cfg.out} changed while this fit read its data (another fit wrote its {MODEL} or "
                            f"{LAST}); run the command again to decide on what it holds now")
        check_run_folder(cfg.out, resume, overwrite)
        aside = SetAside(cfg.out, echo)  # put back if this fit stops before its first checkpoint
        hold.push(aside.__exit__)
        remove_temporaries(cfg.out)  # half-written checkpoints/logs of a killed run (never under their names)
        if state is not None:
            _csv_keep_until(csv_path, step)
        elif os.path.exists(csv_path):  # rows of a run killed before its first checkpoint
            os.unlink(csv_path)
    if world > 1:
        import torch.distributed as dist

        dist.barrier()  # the folder is ready before any rank goes on
    net.train()
    params = list(net.parameters())

    digests: list[str] | None = None  # the ranks' weight digests at the last epoch end (checked equal)
    sums = np.zeros(3)  # Σ loss, error, reg over the current epoch's steps (kept in mid-epoch checkpoints)

    def save(path: str, p: dict) -> None:  # rank 0: a checkpoint, then the replaced run (if any) may go
        ckpt_io.save_checkpoint(path, p)
        if aside is not None:
            aside.drop()

    def payload(epoch: int, batch: int, complete: bool) -> dict:
        return {
            "env": shards.env, "state_names": list(env.state_names), "target_names": list(env.target_names),
            "psi_names": list(shards.psi_names), "resolution": shards.resolution, "manifest_hash": mhash,
            "look": shards.manifest.get("look"), "shards": os.path.abspath(cfg.shards), "seed": cfg.seed, "config": cfg.to_dict(),
            # samples per pixel of the training images (what risp-task --primal-spp can match; docs/tasks.md §Primal spp)
            "spp": shards.manifest.get("spp"),
            "model_config": model_cfg.to_dict(), "normalization": norm.to_dict(), "gamma": gamma,
            "gamma_start": gamma_start,
            "model": net.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
            "progress": {"epoch": epoch, "batch": batch, "global_step": step, "total_steps": total_steps,
                         "complete": complete},
            "history": history, "world_size": world, "workers": cfg.workers, "threads": threads, "cache": cache,
            "device": str(device), "torch_version": torch.__version__, "psi_std": psi_std.tolist(),
            "epoch_sums": [float(v) for v in sums] if batch > 0 else [0.0, 0.0, 0.0],
            "samples": sample_counts(shards), "val": val_rec,
            # the ranks' weight digests at this epoch end (none mid-epoch: they would describe older weights)
            "rank_weights_sha256": digests if batch == 0 else None,
            "rank_resyncs": resyncs,  # --rank-check itself is in "config"
        }

    if rank == 0:
        _write_json(os.path.join(cfg.out, "config.json"),
                    {"config": cfg.to_dict(), "model_config": model_cfg.to_dict(), "gamma": gamma,
                     "gamma_start": gamma_start, "env": shards.env,
                     "manifest_hash": mhash, "normalization": norm.to_dict(), "world_size": world,
                     "threads": threads, "cache": cache, "device": str(device), "steps_per_epoch": plan,
                     "samples": sample_counts(shards), "psi_std": psi_std.tolist(),
                     "versions": {**package_versions(), "risp_commit": risp_commit()}})
    from tqdm.auto import tqdm

    bar = tqdm(total=total_steps, initial=step, disable=(not progress) or rank != 0, unit="step",
               desc=f"fit {shards.env} reg={cfg.reg} {device.type} threads={threads}")

    def note(line: str) -> None:  # a line for the user while the bar is drawn: above it, not across it
        if echo is not None:
            with tqdm.external_write_mode(file=sys.stderr):
                echo(line)
    log = None
    if rank == 0:
        new = not os.path.exists(csv_path)
        log = open(csv_path, "a", newline="")
        writer = csv.DictWriter(log, fieldnames=CSV_FIELDS)
        if new:
            writer.writeheader()
    t_start = time.perf_counter()
    try:
        for epoch in range(epoch0, cfg.epochs):
            skip = batch0 if epoch == epoch0 else 0
            if skip >= plan[epoch]:
                continue
            if mset is not None:
                loader = memory_batches(mset, seed=cfg.seed, epoch=epoch, batch_size=cfg.batch_size, rank=rank,
                                        world_size=world)
            else:
                loader = make_loader(shards, seed=cfg.seed, epoch=epoch, batch_size=cfg.batch_size,
                                     workers=cfg.workers, need_jacobian=need_j, rank=rank, world_size=world,
                                     shuffle_buffer=cfg.shuffle_buffer, state_dim=env.state_dim)
            sums[:] = 0.0
            if skip and partial_sums is not None:  # resumed mid-epoch: the steps before the checkpoint count too
                sums[:] = partial_sums
            for b, batch in enumerate(loader):
                if b >= plan[epoch]:
                    break  # every rank takes exactly plan[epoch] steps
                if b < skip:
                    continue  # already trained on before the resume
                # ---- one optimizer step ------------------------------------------------------------
                g_t = gamma_at(step, total_steps, gamma, cfg.gamma_ramp, gamma_start)
                x, y, tangents = batch_tensors(batch, norm, env, need_j, device)
                reg_t = cfg.reg if g_t > 0 else "none"  # R is not computed (nor logged) while γ(t) = 0
                terms = risp_loss(net, x, y, reg_t, g_t, tangents, step_generator(cfg.seed, rank, step), psi_std)
                if not torch.isfinite(terms.total):
                    raise RispError(f"loss is not finite at step {step} (epoch {epoch}); lower --lr or --gamma")
                opt.zero_grad(set_to_none=True)
                terms.total.backward()
                if world > 1:
                    allreduce_gradients(params, world)
                lr = sched.get_last_lr()[0]
                opt.step()
                sched.step()
                step += 1
                # ---- bookkeeping ---------------------------------------------------------------------
                row = {"step": step, "epoch": epoch, "batch": b, "lr": lr, "gamma": g_t,
                       "loss": float(terms.total.detach()), "error": float(terms.error), "reg": float(terms.reg),
                       "seconds": round(time.perf_counter() - t_start, 4)}
                sums += (row["loss"], row["error"], row["reg"])
                if log is not None:
                    writer.writerow(row)
                    log.flush()
                bar.update(1)
                bar.set_postfix(err=f"{row['error']:.3f}", reg=f"{row['reg']:.3g}")
                if cfg.checkpoint_every and step % cfg.checkpoint_every == 0 and b + 1 < plan[epoch] and rank == 0:
                    save(last_path, payload(epoch, b + 1, False))
                if stop_after_step is not None and step >= stop_after_step:
                    raise TrainingStopped(f"stopped after step {step}")
            n_done = plan[epoch] - (skip if partial_sums is None else 0)
            summary = {"epoch": epoch, "step": step, "train_loss": float(sums[0] / n_done),
                       "train_error": float(sums[1] / n_done), "train_reg": float(sums[2] / n_done), "seconds": round(time.perf_counter() - t_start, 3)}
            if val is not None:
                summary["val_error"] = held_out_error(net, val, norm, env, cfg.val_samples)
            # every epoch: a divergence is caught (or resynced) before it is checkpointed
            digests = agreed_weights(net, opt, world, epoch, cfg.rank_check, resyncs, note)
            history.append(summary)
            sums[:] = 0.0
            if rank == 0:
                save(last_path, payload(epoch + 1, 0, epoch + 1 == cfg.epochs))
                from .plots import plot_losses

                plot_losses(csv_path, os.path.join(cfg.out, "losses.png"), history, cfg.reg, seed=cfg.seed)
            if world > 1:
                import torch.distributed as dist

                dist.barrier()
    finally:
        bar.close()
        if log is not None:
            log.close()
    if digests is None:  # no epoch ran here (a resume at the last epoch's end): the weights are checked once now
        digests = agreed_weights(net, opt, world, cfg.epochs - 1, cfg.rank_check, resyncs, note)
    final = os.path.join(cfg.out, MODEL)
    if rank == 0:
        p = payload(cfg.epochs, 0, True)
        for k in ("optimizer", "scheduler"):
            p.pop(k)
        # history.json first: model.pt is what marks a run finished (risp-task table reuses a run folder that has
        # it), so a run killed between the two must not look finished without its history
        _write_json(os.path.join(cfg.out, "history.json"), history)
        save(final, p)
    return final


