"""The render job: per-shard tasks, per-sample seeds, local-pool and Ray executors, resume.

    job = RenderJob(env="cube", n=10000, out="shards/")
    manifest = run_job(job)

One shard = one task = a contiguous range of sample indices ``[start, stop)``.  Everything random
about sample ``i`` (state, ψ, non-differentiable randomization ``aux``, the renderer's seed) comes from
``np.random.SeedSequence(seed, spawn_key=(i,))`` — the i-th child of the run seed — so a sample does not
depend on the worker count, the shard size or which worker rendered it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import queue as _queue
import shutil
import threading
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .atomic import LOCK_FILE, probe_writable, remove_temporaries
from .atomic import folder_lock as atomic_folder_lock
from .errors import RispError, message_line
from .processes import end_pool_workers, exit_with, start_time
from .ray_support import ray_errors, require_ray
from .threads import available_cpus
from .shards.manifest import (
    FORMAT_NAME,
    FORMAT_VERSION,
    MANIFEST,
    MARKER_DIR,
    identity_mismatch,
    load_manifest,
    marker_path,
    package_versions,
    read_marker,
    save_manifest,
    shard_problem,
    utc_now,
)
from .shards.sample import Sample
from .shards.writer import FORMATS, write_shard
from .shards.layout import storage_block
from .shards.zarr_store import ZARR_DIR, create_store, manifest_shapes, mark_complete_shards

EXECUTORS = ("local", "ray")
SEED_SCHEME = "sample i: np.random.SeedSequence(seed, spawn_key=(i,)); rng = default_rng(it) draws state, then psi/aux; render_seed = its generate_state(1, uint32)[0]"


@dataclass(frozen=True)
class RenderJob:
    """What ``risp-data render`` does, as plain values (docs/cli-data.md)."""

    env: str
    n: int
    out: str
    domain: str = "train"
    formats: tuple[str, ...] = FORMATS
    resolution: int = 64
    spp: int = 16
    seed: int = 0
    workers: int = 1
    shard_size: int = 256
    executor: str = "local"
    jacobian: bool = True
    variant: str | None = None
    jacobian_path: str = "fast"  # risp_data.render.JACOBIAN_PATHS; "legacy" kept for one release (issue 9)
    compact_jacobian: bool = True  # own-channel storage where exact (risp_data.shards.layout); False: all 3

    @property
    def num_shards(self) -> int:
        return -(-self.n // self.shard_size)

    def shard_range(self, shard_index: int) -> tuple[int, int]:
        start = shard_index * self.shard_size
        return start, min(start + self.shard_size, self.n)


def validate_job(job: RenderJob) -> None:
    """Reject bad arguments with one RispError line naming the argument (before anything is touched)."""
    from .envs import get_environment
    from .psi import DOMAINS

    get_environment(job.env)  # unknown names list the valid ones
    if job.domain not in DOMAINS:
        raise RispError(f"unknown domain {job.domain!r}; choose one of: {', '.join(DOMAINS)}")
    for name, option in (("n", "--n"), ("resolution", "--res"), ("spp", "--spp"), ("workers", "--workers"),
                         ("shard_size", "--shard-size")):
        value = getattr(job, name)
        if not isinstance(value, int) or value <= 0:
            raise RispError(f"{option} must be a positive integer, got {value!r}")
    # before anything is written: a huge --n looped for minutes over its shard markers after creating the folder,
    # and a --shard-size beyond --n made zarr allocate the whole shard
    if job.n > MAX_SAMPLES:
        raise RispError(f"--n {job.n} is more than the {MAX_SAMPLES:,} samples one data set may hold")
    if job.shard_size > max(job.n, RenderJob.shard_size):  # the default (256) stays fine for a small --n
        raise RispError(f"--shard-size {job.shard_size} is larger than --n {job.n}: a shard holds at most --n samples")
    if not isinstance(job.seed, int) or job.seed < 0:
        raise RispError(f"--seed must be a non-negative integer, got {job.seed!r}")
    if not str(job.out).strip():  # "" read as "output folder  is not writable"
        raise RispError("--out is empty: give the folder to write the shards to (or leave --out out for the default)")
    if not job.formats or any(f not in FORMATS for f in job.formats):
        raise RispError(f"--format must be one of wds, zarr, both; got {','.join(job.formats) or 'nothing'}")
    if job.executor not in EXECUTORS:
        raise RispError(f"unknown executor {job.executor!r}; choose one of: {', '.join(EXECUTORS)}")
    from .render import JACOBIAN_PATHS

    if job.jacobian_path not in JACOBIAN_PATHS:
        raise RispError(f"--jacobian-path must be one of {', '.join(JACOBIAN_PATHS)}, got {job.jacobian_path!r}")
    check_render_size(job)


# ------------------------------------------------------------------------------------ size limits

MAX_RESOLUTION = 8192
MAX_SAMPLES = 10**9  # per data set: far beyond any run, short of what the shard bookkeeping can loop over
MITSUBA_MAX_SAMPLES = 2**32  # Mitsuba's sampler counts samples of one render pass in a uint32


def memory_estimate(job: RenderJob, k: int) -> int:
    """Bytes a render job needs at its peak, roughly: per worker, one shard's samples held before writing
    (image + K Jacobian slices, float32 RGB) plus the renderer's film and K tangent buffers (float32 RGBA and
    a float64 accumulator, ≈ 3× one image each) — a lower bound used to refuse hopeless jobs up front."""
    pixels = job.resolution * job.resolution
    per_sample = (1 + (k if job.jacobian else 0)) * pixels * 3 * 4
    held = min(job.shard_size, job.n) * per_sample
    renderer = (2 + (k if job.jacobian else 0)) * pixels * 4 * 4 * 3
    workers = 1 if job.executor == "ray" else min(job.workers, job.num_shards)
    return workers * (held + renderer)


def available_memory() -> int | None:
    """Bytes this process may still use: the smallest of MemAvailable (where /proc/meminfo lacks it, the free
    physical pages), the cgroup limit and RLIMIT_AS; None where none is known.  The one rule for rendering's
    memory check, make-video's and risp-train's ``--cache auto``."""
    import resource

    limits = []
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    limits.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    if not limits:
        try:
            limits.append(int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE")))
        except (ValueError, OSError, AttributeError):
            pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path) as f:
                text = f.read().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < 2**60:
            limits.append(int(text))
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        limits.append(int(soft))
    return min(limits) if limits else None


def check_image_size(resolution: int, spp: int, domain: str, option: str = "--res") -> None:
    """Refuse images Mitsuba cannot render: sides above MAX_RESOLUTION, or more samples in one pass than its
    uint32 counter holds (the domain's spp factor included: the target domain renders 4× --spp)."""
    from .render import DOMAIN_SETTINGS

    if resolution > MAX_RESOLUTION:
        raise RispError(f"{option} {resolution} is larger than the supported {MAX_RESOLUTION} pixels")
    settings = DOMAIN_SETTINGS.get(domain)
    samples = resolution * resolution * spp * (settings.spp_factor if settings is not None else 1)
    if samples >= MITSUBA_MAX_SAMPLES:
        raise RispError(f"{option} {resolution} with --spp {spp} needs {samples:,} samples per pass in the {domain} "
                        f"domain, beyond Mitsuba's limit of 2^32; lower {option} or --spp")


def check_render_size(job: RenderJob) -> None:
    """Refuse, before anything is written, image sizes Mitsuba cannot render or this machine cannot hold."""
    from .psi import psi_specs

    check_image_size(job.resolution, job.spp, job.domain)
    need = memory_estimate(job, len(psi_specs(job.env)))
    have = available_memory()
    if have is not None and need > have:
        raise RispError(f"--res {job.resolution} needs about {need / 2**30:.1f} GiB of memory "
                        f"({min(job.workers, job.num_shards)} worker(s), --shard-size {job.shard_size}); "
                        f"{have / 2**30:.1f} GiB are available: lower --res, --shard-size or --workers")


# ------------------------------------------------------------------------------------ one sample


@dataclass(frozen=True)
class SampleInputs:
    """Everything random about one sample, derived from (run seed, global index) alone."""

    index: int
    state: np.ndarray  # (S,) float64
    config: Any  # risp_data.psi.RenderConfig: psi (K,) float64 + aux dict
    render_seed: int


def sample_inputs(env, domain: str, seed: int, index: int) -> SampleInputs:
    """State, ψ/aux and render seed of sample ``index`` of a run with seed ``seed`` (see module docstring)."""
    from .psi import sample_rendering

    ss = np.random.SeedSequence(seed, spawn_key=(index,))
    rng = np.random.default_rng(ss)
    state = np.asarray(env.sample_states(rng, 1), dtype=np.float64)[0]
    config = sample_rendering(env.name, domain, rng)
    render_seed = int(ss.generate_state(1, np.uint32)[0])
    return SampleInputs(index=index, state=state, config=config, render_seed=render_seed)


def jsonable(obj: Any) -> Any:
    """Plain-JSON copy of ``obj`` (numpy scalars/arrays become numbers/lists)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def render_sample(renderer, env, job: RenderJob, index: int, config=None) -> Sample:
    """Render sample ``index``: image and (unless ``job.jacobian`` is off) its forward-mode Jacobian stack.
    ``config``: a rendering configuration in place of the sample's own draw (risp-train ablation's ψ pool); the
    state and render seed stay the sample's."""
    inp = sample_inputs(env, job.domain, job.seed, index)
    if config is not None:
        inp = dataclasses.replace(inp, config=config)
    if job.jacobian:
        image, jac = renderer.render(inp.state, inp.config, inp.render_seed, jacobian=True)
    else:  # image only: the domain's reference integrator (target domain: Mitsuba's `path`)
        image, jac = renderer.render_reference(inp.state, inp.config, inp.render_seed), None
    # a NaN in one training sample poisons every step that sees it: refuse to store it
    if not np.isfinite(image).all():
        raise RispError(f"sample {index} of {job.env}/{job.domain}: the renderer returned a non-finite image")
    if jac is not None and not np.isfinite(jac).all():
        bad = [n for n, j in zip(renderer.psi_names, jac) if not np.isfinite(j).all()]
        raise RispError(f"sample {index} of {job.env}/{job.domain}: non-finite Jacobian for {', '.join(bad)}")
    meta = {
        "env": job.env,
        "domain": job.domain,
        "index": index,
        "seed": job.seed,
        "render_seed": inp.render_seed,
        "state_names": list(env.state_names),
        "psi_names": list(renderer.psi_names),
        "aux": jsonable(inp.config.aux),
        "resolution": job.resolution,
        "spp": job.spp,
        "variant": getattr(renderer, "variant", job.variant),
        "jacobian": job.jacobian,
        "integrator": renderer.settings.integrator if job.jacobian else renderer.image_integrator,
    }
    return Sample(
        index=index,
        image=np.asarray(image, dtype=np.float32),
        jacobian=None if jac is None else np.asarray(jac, dtype=np.float32),
        state=inp.state,
        psi=np.asarray(inp.config.psi, dtype=np.float64),
        meta=meta,
    )


def make_renderer(job: RenderJob, threads: int | None = None):
    """Set up Mitsuba (LLVM check, variant) and build the job's Renderer once per process."""
    from .envs import get_environment
    from .mitsuba_setup import init_mitsuba
    from .render import Renderer

    init_mitsuba(job.variant)
    if threads is not None:
        from .threads import set_drjit_threads

        set_drjit_threads(threads)
    get_environment(job.env)
    return Renderer(job.env, domain=job.domain, resolution=job.resolution, spp=job.spp, variant=job.variant,
                    jacobian_path=job.jacobian_path)


def render_shard(job: RenderJob, shard_index: int, renderer, on_sample: Callable[[], None] | None = None) -> dict:
    """The shard task: render samples [start, stop) and write them in every format; returns the record."""
    from .envs import get_environment

    env = get_environment(job.env)
    start, stop = job.shard_range(shard_index)
    samples = []
    for i in range(start, stop):
        samples.append(render_sample(renderer, env, job, i))
        if on_sample is not None:
            on_sample()
    return write_shard(job.out, job.formats, shard_index, samples)


# ------------------------------------------------------------------------------- folder + manifest


def new_manifest(job: RenderJob, variant: str) -> dict[str, Any]:
    from .envs import get_environment
    from .envs.look import look_fingerprint
    from .psi import own_channels, psi_manifest

    env = get_environment(job.env)
    psi = psi_manifest(job.env, job.domain)  # the folder domain's ranges and units, what J is w.r.t.
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "env": job.env,
        "look": look_fingerprint(job.env),
        "domain": job.domain,
        "resolution": job.resolution,
        "spp": job.spp,
        "variant": variant,
        "jacobian": job.jacobian,
        "n": job.n,
        "shard_size": job.shard_size,
        "num_shards": job.num_shards,
        "seed": job.seed,
        "seed_scheme": SEED_SCHEME,
        "formats": list(job.formats),
        "psi": psi,
        "jacobian_storage": storage_block(psi["names"], own_channels(job.env), job.compact_jacobian and job.jacobian),
        "state_names": list(env.state_names),
        "state_low": [float(v) for v in env.state_low],
        "state_high": [float(v) for v in env.state_high],
        "versions": package_versions(),
        "args": jsonable(dataclasses.asdict(job)),
        "created": utc_now(),
        "shards": [],
    }


def _check_writable(folder: str) -> None:
    try:
        probe_writable(folder)
    except OSError as e:
        raise RispError(f"output folder {folder} is not writable: {e.strerror or e}") from None


def _zarr_store_ok(folder: str, manifest: dict[str, Any]) -> bool:
    """The store's metadata is there and readable: its root group and every array the manifest's job has, each of
    the job's shape (a deleted, truncated or hand-edited zarr.json is a damaged store, not a complete one)."""
    shapes = manifest_shapes(manifest)
    store = os.path.join(folder, ZARR_DIR)
    if not (os.path.exists(os.path.join(store, "zarr.json"))
            and all(os.path.exists(os.path.join(store, name, "zarr.json")) for name in shapes)):
        return False
    import zarr

    try:
        root = zarr.open_group(store, mode="r")
        return all(tuple(root[name].shape) == tuple(shape) for name, shape in shapes.items())
    except zarr.errors.UnknownCodecError as e:  # this zarr lacks the store's codec: the library, not the data
        raise RispError(f"zarr store {store}: {message_line(e)} (zarr {zarr.__version__} cannot read it; the store "
                        "was left as it is: use the zarr version that wrote it)") from None
    except (ValueError, KeyError, TypeError, IndexError):  # damaged metadata: bad JSON (ValueError), failed
        return False  # validation (zarr's errors are ValueErrors), missing or mistyped fields
    except OSError as e:  # permissions, too many open files, …: not a damaged store, and nothing may be deleted
        raise RispError(f"zarr store {store}: cannot read its metadata ({e.strerror or message_line(e)}); the store "
                        "was left as it is") from None


def _remove_temporaries(folder: str) -> None:
    """Delete the temporaries a killed run left behind: our ``.tmp-*`` files and zarr's ``*.partial`` files
    (never visible to readers, safe to drop)."""
    for sub in ("", "wds", MARKER_DIR):
        remove_temporaries(os.path.join(folder, sub))
    for root, _, files in os.walk(os.path.join(folder, ZARR_DIR)):
        for name in files:
            if name.endswith(".partial"):
                os.unlink(os.path.join(root, name))


def _shard_files(manifest: dict[str, Any], shard_index: int) -> list[str]:
    """Relative paths of every file shard ``shard_index`` has in the folder's formats."""
    from .shards.wds import shard_name
    from .shards.zarr_store import shard_file

    rels = [shard_name(shard_index)] if "wds" in manifest["formats"] else []
    if "zarr" in manifest["formats"]:
        shapes = manifest_shapes(manifest, n=1, resolution=1)
        rels += [shard_file("", name, shard_index, len(shape)) for name, shape in shapes.items()]
    return rels


def _drop_unlisted_shards(folder: str, manifest: dict[str, Any]) -> None:
    """Delete the files of every shard the manifest does not list (killed or damaged writes), zarr's ``states``
    first, so plain zarr readers see such samples as unwritten (NaN) rather than half written."""
    listed = {r["index"] for r in manifest["shards"]}
    for i in range(manifest["num_shards"]):
        if i in listed:
            continue
        for rel in sorted(_shard_files(manifest, i), key=lambda r: "/states/" not in r):
            path = os.path.join(folder, rel)
            if os.path.exists(path):
                os.unlink(path)
        marker = marker_path(folder, i)
        if os.path.exists(marker):
            os.unlink(marker)


def _drop_damaged_shards(folder: str, manifest: dict[str, Any], log: Callable[[str], None]) -> bool:
    """Remove listed shards whose files are missing or differ from the manifest (size, then sha256) from
    the manifest, so that they are rendered again; True when any was removed."""
    damaged = []
    if manifest["shards"]:
        log(f"checking the {len(manifest['shards'])} listed shard(s) of {folder} (sizes, sha256)")
    for rec in sorted(manifest["shards"], key=lambda r: r["index"]):
        why = shard_problem(folder, rec, deep=True)
        if why is not None:
            log(f"shard {rec['index']} is damaged ({why}): rendering it again")
            damaged.append(rec["index"])
    manifest["shards"] = [r for r in manifest["shards"] if r["index"] not in damaged]
    return bool(damaged)


@contextlib.contextmanager
def folder_lock(folder: str):
    """Hold an exclusive lock on ``folder/.lock`` so two render jobs never write the same folder."""
    with atomic_folder_lock(folder, f"another risp-data render is writing to {folder}; wait for it or stop it"):
        yield


def _is_fresh(folder: str) -> bool:
    """True when ``folder`` holds nothing but our lock file and temporaries (a run killed at its start)."""
    return all(name == LOCK_FILE or name.startswith(".tmp-") for name in os.listdir(folder))


def _holds_no_samples(folder: str) -> bool:
    """True when a folder's job never finished a shard (no listed shard, no marker): a job that failed at its
    start (say, an image size the renderer refused) must not block the folder for a corrected command."""
    markers = os.path.join(folder, MARKER_DIR)
    return not load_manifest(folder)["shards"] and not (os.path.isdir(markers) and os.listdir(markers))


def check_folder(job: RenderJob, variant: str, psi_pool: dict | None = None) -> None:
    """Refuse, without touching anything, a folder that holds another job or foreign files.

    ``psi_pool``: the manifest record of a pool of looks (risp-train ablation: sample i renders with pool[i mod
    P]) the caller renders with.  A folder rendered with a pool is resumed only with the same pool — risp-data
    render, verify --repair and a plain resume would give its missing samples their own looks."""
    out = job.out
    if os.path.exists(out) and not os.path.isdir(out):
        raise RispError(f"output path {out} exists and is not a folder")
    if not os.path.isdir(out):
        return
    if os.path.exists(os.path.join(out, MANIFEST)):
        manifest = load_manifest(out)
        diffs = identity_mismatch(manifest, new_manifest(job, variant))
        holds_samples = not _holds_no_samples(out)
        if diffs and holds_samples:
            raise RispError(f"output folder {out} holds another job ({'; '.join(diffs)}); give a new folder with --out "
                            f"(or remove {out})")
        held = manifest.get("psi_pool")
        if holds_samples and not _same_pool(held, psi_pool):
            if psi_pool is None:
                raise RispError(f"{out} was rendered by risp-train ablation with a pool of {held.get('size')} "
                                "look(s) (manifest psi_pool): risp-data cannot re-render its samples (they would get "
                                "looks of their own); run that ablation command again, which resumes the folder")
            other = "without a pool of looks" if held is None else "with another pool of looks"
            raise RispError(f"output folder {out} holds samples rendered {other}; give a new folder with --out "
                            f"(or remove {out})")
    elif not _is_fresh(out):
        raise RispError(f"output folder {out} is not empty and has no {MANIFEST}; use an empty or new folder")


def _same_pool(held: dict | None, pool: dict | None) -> bool:
    """Whether two ``psi_pool`` records name the same looks (both None: no pool)."""
    if held is None or pool is None:
        return held is None and pool is None
    return held.get("size") == pool.get("size") and held.get("psi") == pool.get("psi")


def prepare_folder(job: RenderJob, variant: str, log: Callable[[str], None] = print,
                   psi_pool: dict | None = None) -> dict[str, Any]:
    """Open (resume) or create the output folder; returns its manifest with marker-only shards merged and
    damaged shards (a listed file missing, truncated or with another sha256) dropped for re-rendering.

    Call with the folder lock held, after :func:`check_folder`.
    """
    out = job.out
    check_folder(job, variant, psi_pool)
    manifest = load_manifest(out) if os.path.exists(os.path.join(out, MANIFEST)) else None
    if manifest is None or identity_mismatch(manifest, new_manifest(job, variant)):  # new, or an empty job's
        manifest = new_manifest(job, variant)
        save_manifest(out, manifest)
        if "zarr" in job.formats:
            create_store(out, manifest)
    _remove_temporaries(out)
    if "zarr" in job.formats and not _zarr_store_ok(out, manifest):
        if manifest["shards"]:  # the store holds every shard's samples: made anew, they are all rendered again
            log(f"zarr store {os.path.join(out, ZARR_DIR)} is damaged (its metadata is missing or unreadable): "
                f"making it anew and rendering its {len(manifest['shards'])} complete shard(s) again")
            manifest["shards"] = []
            save_manifest(out, manifest)
            _drop_unlisted_shards(out, manifest)  # their files and markers: every shard is unlisted now
        create_store(out, manifest)
    # shards whose marker was written but whose manifest update was lost (killed in between)
    done = {r["index"] for r in manifest["shards"]}
    changed = False
    for i in range(job.num_shards):
        if i not in done:
            rec = read_marker(out, i)
            if rec is not None and (rec["start"], rec["stop"]) == job.shard_range(i):
                manifest["shards"].append(rec)
                changed = True
    changed |= _drop_damaged_shards(out, manifest, log)
    if changed:
        save_manifest(out, manifest)
    _drop_unlisted_shards(out, manifest)
    if "zarr" in job.formats:
        mark_complete_shards(out, manifest)
    return manifest


# ----------------------------------------------------------------------------------------- executors

_WORKER: dict[str, Any] = {}


# What every render worker imports before it renders (torch for the environments' meshes, the shard writers).
# A fork server imports them once; each worker is a fork of it (start-up, docs/PERFORMANCE.md).  mitsuba and
# drjit are not among them: they start threads, and a worker sets up its own LLVM (init_mitsuba) after the fork.
WORKER_PRELOAD = ("torch", "risp_data.envs", "risp_data.psi", "risp_data.shards.writer", "zarr", "webdataset",
                  "OpenEXR", "risp_data.generate")


def worker_context():
    """The render pool's multiprocessing context: a fork server that has done WORKER_PRELOAD's imports (once,
    single-threaded, so forking it is safe), started now so that those imports overlap the parent's own set-up;
    ``spawn`` where there is no fork server (each worker then imports everything itself)."""
    import multiprocessing as mp

    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    from multiprocessing import forkserver

    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(list(WORKER_PRELOAD))
    forkserver.ensure_running()  # returns at once; the server imports in the background
    return ctx


def _worker_init(job: RenderJob, threads: int, progress_queue, job_pid: int | None = None,
                 job_started: str | None = None) -> None:
    import torch

    if job_pid is not None:
        exit_with(job_pid, job_started)  # forks of the fork server, not the job's children: they end with the job
    torch.set_num_threads(1)
    _WORKER["renderer"] = make_renderer(job, threads)
    _WORKER["queue"] = progress_queue
    _WORKER["job"] = job


def _worker_run(shard_index: int) -> dict:
    q = _WORKER["queue"]
    return render_shard(_WORKER["job"], shard_index, _WORKER["renderer"], on_sample=lambda: q.put(1))


def _run_inline(job, todo, on_record, bar):
    """Render in this process: Dr.Jit on the CPUs this process may use, as the pool's workers share them (set, not
    Dr.Jit's implicit default), and one torch thread, as each worker has — both restored afterwards: a caller's
    counts are its own (a table run renders its test sets in process between cells that run on one thread)."""
    from .mitsuba_setup import init_mitsuba
    from .threads import drjit_threads, torch_threads

    init_mitsuba(job.variant)  # the libLLVM check comes before drjit is first imported
    with torch_threads(1), drjit_threads(available_cpus()):
        renderer = make_renderer(job)
        for i in todo:
            on_record(render_shard(job, i, renderer, on_sample=lambda: bar.update(1)))


def _run_pool(job, todo, on_record, bar):
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = worker_context()
    q = ctx.Queue()
    workers = min(job.workers, len(todo))
    threads = max(1, available_cpus() // workers)  # the affinity mask's CPUs (taskset), not the host's
    stop = threading.Event()

    def drain():
        while not stop.is_set():
            try:
                bar.update(q.get(timeout=0.2))
            except _queue.Empty:
                pass

    t = threading.Thread(target=drain, daemon=True)
    t.start()
    try:
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init,
                                 initargs=(job, threads, q, os.getpid(), start_time(os.getpid()))) as ex:
            pending = {ex.submit(_worker_run, i) for i in todo}
            try:
                while pending:
                    finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in finished:
                        on_record(f.result())
            except BaseException:  # Ctrl-C, or a shard that failed: the workers stop now, not after the shards
                end_pool_workers(ex)  # already queued to them (a finished one is kept: its completion marker)
                raise
    finally:
        stop.set()
        t.join()


def ray_actor_count(workers: int, shards: int, cluster_cpus: int) -> int:
    """Ray actors for a render: ``--workers``, but no more than the shards to render or the cluster's CPUs (each
    actor holds at least one CPU while it lives)."""
    return max(1, min(workers, shards, cluster_cpus))


def _run_ray(job, todo, on_record, bar):
    """The same shard tasks on Ray actors (a running cluster when RAY_ADDRESS is set, else a local one)."""
    ray = require_ray()
    from ray.util import ActorPool

    if not ray.is_initialized():
        ray.init()

    # as the local pool: the CPUs this process may use, shared by the actors that start (not os.cpu_count(), which
    # ignores taskset and oversubscribed Dr.Jit).  Never more actors than the cluster has CPUs: an actor that cannot
    # be scheduled still gets shards from the ActorPool, which then waits for it for ever.
    cluster_cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
    actors_n = ray_actor_count(job.workers, len(todo), cluster_cpus)
    threads = max(1, min(available_cpus(), cluster_cpus) // actors_n)
    # Ray workers need not share this process's working directory (a cluster's never do): absolute paths
    job = dataclasses.replace(job, out=os.path.abspath(job.out))

    @ray.remote
    class ShardActor:  # one Renderer per actor, reused for all its shards
        def __init__(self, job, threads):
            import torch

            torch.set_num_threads(1)  # as the pool's workers: torch only stores the samples
            self.renderer = make_renderer(job, threads)
            self.job = job

        def run(self, shard_index):
            return render_shard(self.job, shard_index, self.renderer)

    actors = [ShardActor.options(num_cpus=threads).remote(job, threads) for _ in range(actors_n)]
    pool = ActorPool(actors)
    with ray_errors("rendering a shard"):
        for rec in pool.map_unordered(lambda a, i: a.run.remote(i), list(todo)):
            bar.update(rec["stop"] - rec["start"])
            on_record(rec)


def run_job(job: RenderJob, progress: bool = True, log: Callable[[str], None] = print,
            stats: dict | None = None) -> dict[str, Any]:
    """Render every missing or damaged shard of ``job`` into ``job.out`` and return the final manifest.

    ``stats``, when given, receives ``rendered_samples``: the samples rendered by this call.
    """
    from .mitsuba_setup import init_mitsuba

    if job.executor == "local" and isinstance(job.workers, int) and job.workers > 1:
        worker_context()  # start the pool's fork server first: its imports overlap validation and set-up
    validate_job(job)
    if job.executor == "ray":
        require_ray()  # fail before anything is written
    variant = init_mitsuba(job.variant)  # fails with one line when no usable libLLVM exists
    check_folder(job, variant)  # refuse another job's folder before creating or locking anything
    _check_writable(job.out)
    with folder_lock(job.out):
        return _run_locked(job, variant, progress, log, stats)


def _check_space(job: RenderJob, manifest: dict) -> None:
    """Stop a render that will not fit on its disk now, with the shards so far kept, rather than when the disk is
    full (ours and every other program's writes then fail): the samples still to render, at the bytes per sample
    of the shards written so far, against the free space of ``job.out``'s file system."""
    written = manifest["shards"]
    samples = sum(r["stop"] - r["start"] for r in written)
    if not samples:
        return
    per_sample = sum(info["bytes"] for r in written for info in r["files"].values()) / samples
    need = per_sample * (job.n - samples)
    usage = shutil.disk_usage(job.out)
    # the shards being written beside this one (one per worker) already hold part of their share of the disk
    in_flight = per_sample * job.shard_size * (job.workers if isinstance(job.workers, int) else 1)
    if usage.total > 0 and need - in_flight > usage.free:  # total 0: a file system that reports no sizes
        free = usage.free
        raise RispError(f"{job.out}: the {job.n - samples} samples still to render need about {need / 1e9:.3g} GB "
                        f"(at {per_sample / 1e3:.0f} kB per sample so far) but {free / 1e9:.3g} GB are free there; "
                        f"the {len(written)} finished shard(s) are kept: free space and rerun the same command to "
                        f"resume, or render fewer samples into another --out")


def version_changes(recorded: dict, now: dict) -> list[str]:
    """``name old (now new)`` for every package whose recorded version differs from the installed one."""
    return [f"{k} {recorded[k]} (now {now.get(k)})" for k in sorted(recorded) if recorded[k] != now.get(k)]


def _run_locked(job: RenderJob, variant: str, progress: bool, log: Callable[[str], None],
                stats: dict | None) -> dict[str, Any]:
    from tqdm import tqdm

    manifest = prepare_folder(job, variant, log)
    layout = (manifest.get("jacobian_storage") or {}).get("layout", "full")
    if manifest["shards"] and layout != new_manifest(job, variant)["jacobian_storage"]["layout"]:
        log(f"{job.out} stores Jacobians in the {layout} layout: its missing shards keep that layout")
    done = {r["index"] for r in manifest["shards"]}
    todo = [i for i in range(job.num_shards) if i not in done]
    if done:
        log(f"resuming {job.out}: {len(done)} of {job.num_shards} shards complete, rendering {len(todo)}")
        changed = version_changes(manifest.get("versions") or {}, package_versions())
        if changed and todo:  # the manifest keeps the versions it was created with: say that the new shards differ
            log(f"note: {job.out} was rendered with {', '.join(changed)}; its missing shards are rendered with the "
                "versions installed now (samples may differ from an uninterrupted run in rounding)")
    if not todo:  # the folder's manifest as saved (counts, complete), also after markers were merged above
        return load_manifest(job.out)
    lock = threading.Lock()

    def on_record(rec):
        with lock:
            manifest["shards"] = [r for r in manifest["shards"] if r["index"] != rec["index"]] + [rec]
            save_manifest(job.out, manifest)
            if "zarr" in job.formats:
                mark_complete_shards(job.out, manifest)
            if stats is not None:
                stats["rendered_samples"] = stats.get("rendered_samples", 0) + rec["stop"] - rec["start"]
            _check_space(job, manifest)

    total = sum(job.shard_range(i)[1] - job.shard_range(i)[0] for i in todo)
    with tqdm(total=total, unit="sample", desc=f"render {job.env}/{job.domain}", disable=not progress) as bar:
        if job.executor == "ray":
            _run_ray(job, todo, on_record, bar)
        elif job.workers == 1 or len(todo) == 1:
            _run_inline(job, todo, on_record, bar)
        else:
            _run_pool(job, todo, on_record, bar)
    return load_manifest(job.out)
