"""``risp-data verify``: check stored Jacobians against central differences of re-renders.

For each chosen sample i, the state, ψ, aux and render seed are re-derived from (run seed, i)
(risp_data.generate.sample_inputs) and must equal the stored ones.  Then, for every ψ_j,

    J_j^FD = (I(ψ + h_j e_j) − I(ψ − h_j e_j)) / (2 h_j),   h_j = eps · (high_j − low_j),

rendered with the same seed (the same light paths, so Monte-Carlo noise cancels), and

    err_j = ‖J_j^stored − J_j^FD‖ / ‖J_j^FD‖       (norms pooled over all chosen samples)

must be ≤ tol.  The re-rendered primal is compared with the stored image as well (determinism).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .envs.look import look_fingerprint
from .errors import RispError
from .shards import load_manifest, verify_checksums
from .shards.reader import complete_indices, read_samples


# Defaults (docs/cli-data.md, "verify"; issue 9).  The FD step h_j = EPS · (high_j − low_j) of the folder
# domain's ψ range.  With same-seed renders the only error left in J^FD is the float32 rounding of the
# two images divided by 2h (it grows as 1/EPS) plus an O(h²) truncation term (I is linear in the
# emitter ψ and a low-degree polynomial in the reflectances).  Measured at EPS = 1e-2, 64×64, 16 spp,
# every environment and domain: pooled rel. error ≤ 1.4e-5, worst single sample 2.5e-5.  TOL = 1e-3
# leaves a 40× margin for that noise (smaller images, other machines) and still fails any J off by
# 0.1 %: a wrong sign, a missing bounce, another seed's paths or a mis-scaled tangent are 1–100 % off.
EPS = 1e-2
TOL = 1e-3
MAX_EPS = 0.1  # largest finite-difference step, as a fraction of each ψ's range


@dataclass(frozen=True)
class VerifyConfig:
    folder: str
    samples: int = 8
    eps: float = EPS
    tol: float = TOL
    checksums: bool = True
    progress: bool = True
    repair: bool = False  # first re-render every listed shard whose files are missing or damaged


@dataclass
class VerifyReport:
    folder: str
    indices: list[int]
    psi_names: list[str]
    rel_error: list[float]  # pooled over samples, per ψ_j
    max_sample_error: list[float]  # worst single sample, per ψ_j
    image_error: float  # max |stored − re-rendered| / max |stored|
    files_checked: int
    tol: float
    failures: list[str] = field(default_factory=list)
    repaired: int | None = None  # samples re-rendered by --repair (None: no repair asked for)
    jacobian: bool = True  # False: a --no-jacobian folder, whose repair and checksums were all there was to do
    compared: list[int] | None = None  # the samples whose Jacobians were compared (None: all of ``indices``)

    def raise_if_failed(self) -> None:
        if self.failures:
            raise RispError(f"verify failed for {self.folder}: " + "; ".join(self.failures))


def format_report(r: VerifyReport) -> str:
    lines = [] if r.repaired is None else [f"repair: {r.repaired} sample(s) re-rendered"]
    lines.append(f"checksums: {r.files_checked} shard files ok" if r.files_checked else "checksums: skipped")
    if not r.jacobian:
        return "\n".join(lines + ["no Jacobians to verify: the folder was rendered with --no-jacobian"])
    compared = r.indices if r.compared is None else r.compared
    if not compared:  # every chosen sample failed before its Jacobian was compared: no ψ line can say "ok"
        return "\n".join(lines + [f"chosen samples {r.indices}: none compared (see the failures below)"])
    lines += [
        f"re-rendered samples {compared}; primal vs stored image: max rel. difference {r.image_error:.2e}",
        f"{'psi':<18} {'rel.error':>10} {'worst sample':>13}   (tolerance {r.tol:g})",
    ]
    for name, e, w in zip(r.psi_names, r.rel_error, r.max_sample_error):
        lines.append(f"{name:<18} {e:10.2e} {w:13.2e}   {'ok' if e <= r.tol else 'FAIL'}")
    return "\n".join(lines)


def repair_folder(folder: str, progress: bool = True, log=print) -> int:
    """Re-render the shards of ``folder`` that are missing, truncated or damaged (size or sha256 differ from
    the manifest) with the job recorded in its manifest — no hand-editing; returns the samples re-rendered."""
    from .generate import RenderJob, run_job

    m = load_manifest(folder)
    known = {f.name for f in dataclasses.fields(RenderJob)}
    args = {k: v for k, v in m.get("args", {}).items() if k in known}
    if not args:
        raise RispError(f"manifest of {folder} does not record its render job (args); cannot repair it")
    # the folder's own variant (a repair on a GPU machine of a folder rendered on a CPU must not switch to CUDA:
    # another variant is another job); the pool that rendered it may not exist here (a ray cluster, more CPUs)
    from .threads import available_cpus

    args.update(out=folder, formats=tuple(args.get("formats", m["formats"])), variant=m.get("variant", args.get("variant")),
                executor="local", workers=max(1, min(int(args.get("workers", 1)), available_cpus())))
    stats: dict = {}
    run_job(RenderJob(**args), progress=progress, log=log, stats=stats)
    return int(stats.get("rendered_samples", 0))


def _pool_configs(m: dict, folder: str) -> list | None:
    """The looks of a folder risp-train ablation rendered with a pool (manifest ``psi_pool``), else None; a record
    without the looks' aux (written before 2026-12-02) cannot be re-rendered: one line says so."""
    from .psi import RenderConfig

    rec = m.get("psi_pool")
    if rec is None:
        return None
    if "aux" not in rec:
        raise RispError(f"{folder} was rendered with a pool of looks whose record lacks their aux (an older risp-train "
                        "ablation): its samples cannot be re-rendered; run the ablation command again (it adds them)")
    return [RenderConfig(psi=np.asarray(p, dtype=np.float64), aux=a) for p, a in zip(rec["psi"], rec["aux"])]


def _nan_max(a: float, b: float) -> float:
    """max(a, b) that keeps a NaN (Python's max drops it when it comes second): a non-finite error must fail."""
    return b if not b <= a else a


def verify_folder(cfg: VerifyConfig) -> VerifyReport:
    from tqdm import tqdm

    from .envs import get_environment
    from .generate import RenderJob, make_renderer, sample_inputs

    if cfg.samples <= 0:
        raise RispError(f"--samples must be a positive integer, got {cfg.samples}")
    if not cfg.eps > 0 or not cfg.tol > 0:
        raise RispError(f"--eps and --tol must be positive, got {cfg.eps} and {cfg.tol}")
    if cfg.eps > MAX_EPS:  # ψ ± h would leave ψ's range by far (negative reflectances): not a derivative check
        raise RispError(f"--eps {cfg.eps:g} is a step of {cfg.eps:g}× each ψ's range; use at most {MAX_EPS:g} "
                        "(default 1e-2)")
    repaired = repair_folder(cfg.folder, cfg.progress) if cfg.repair else None
    m = load_manifest(cfg.folder)
    if not m["jacobian"] and not cfg.repair:
        raise RispError(f"{cfg.folder} was rendered with --no-jacobian: there are no Jacobians to verify "
                        f"(--repair still re-renders its damaged shards)")
    files = verify_checksums(cfg.folder, m) if cfg.checksums else 0  # a damaged file's error names the repair
    if not m["jacobian"]:  # repaired and checked: there is nothing more to compare
        return VerifyReport(cfg.folder, [], [], [], [], 0.0, files, cfg.tol, repaired=repaired, jacobian=False)
    look = look_fingerprint(m["env"])
    if m.get("look") != look:  # the re-renders would show another object than the stored images
        raise RispError(f"{cfg.folder} was rendered with another look of {m['env']} (look {m.get('look')}, risp "
                        f"draws {look} now: docs/environments.md §Appearance); its Jacobians cannot be re-rendered")
    indices = complete_indices(m)
    if not indices:
        raise RispError(f"{cfg.folder} has no complete shard yet")
    chosen = sorted({indices[int(i)] for i in np.linspace(0, len(indices) - 1, min(cfg.samples, len(indices)))})
    stored = read_samples(cfg.folder, chosen)
    env = get_environment(m["env"])
    job = RenderJob(env=m["env"], n=m["n"], out=cfg.folder, domain=m["domain"], resolution=m["resolution"],
                    spp=m["spp"], seed=m["seed"], shard_size=m["shard_size"], variant=m["variant"])
    from .threads import available_cpus

    renderer = make_renderer(job, available_cpus())  # Dr.Jit's threads set, not left to its implicit default
    pool = _pool_configs(m, cfg.folder)
    low, high = np.asarray(m["psi"]["low"]), np.asarray(m["psi"]["high"])
    h = cfg.eps * (high - low)
    k = len(h)
    num = np.zeros(k)  # Σ_samples ‖J_stored − J_FD‖²
    den = np.zeros(k)  # Σ_samples ‖J_FD‖²
    worst = np.zeros(k)
    image_err = 0.0
    failures = []
    skipped: set[int] = set()  # samples that failed before their Jacobian was compared
    for i in tqdm(chosen, desc="verify", unit="sample", disable=not cfg.progress):
        s = stored[i]
        inp = sample_inputs(env, m["domain"], m["seed"], i)
        if pool is not None:  # risp-train ablation's pool of looks: sample i rendered with pool[i mod P]
            inp = dataclasses.replace(inp, config=pool[i % len(pool)])
        if not (np.array_equal(inp.state, s["state"]) and np.array_equal(np.asarray(inp.config.psi), s["psi"])):
            failures.append(f"sample {i}: stored state/psi differ from the ones its seed gives")
            skipped.add(i)
            continue
        image, _ = renderer.render(inp.state, inp.config, inp.render_seed, jacobian=False)
        if not (np.all(np.isfinite(s["image"])) and np.all(np.isfinite(s["jacobian"]))):
            failures.append(f"sample {i}: the stored image or Jacobian holds NaN or inf")
            skipped.add(i)
            continue
        scale = max(float(np.abs(s["image"]).max()), 1e-12)
        err = float(np.abs(np.asarray(image) - s["image"]).max()) / scale
        image_err = _nan_max(image_err, err)
        for j in range(k):
            imgs = []
            for sign in (1.0, -1.0):
                psi = np.array(inp.config.psi, dtype=np.float64)
                psi[j] += sign * h[j]
                img, _ = renderer.render(inp.state, dataclasses.replace(inp.config, psi=psi), inp.render_seed,
                                         jacobian=False)
                imgs.append(np.asarray(img, dtype=np.float64))
            fd = (imgs[0] - imgs[1]) / (2.0 * h[j])
            diff = float(np.sum((s["jacobian"][j].astype(np.float64) - fd) ** 2))
            norm = float(np.sum(fd**2))
            num[j] += diff
            den[j] += norm
            err_j = float(np.sqrt(diff / max(norm, 1e-30)))
            worst[j] = _nan_max(worst[j], err_j)
    rel = np.sqrt(num / np.maximum(den, 1e-30))
    names = list(m["psi"]["names"])
    compared = [i for i in chosen if i not in skipped]
    # "not <=": a NaN (a re-render or finite difference gone non-finite) fails instead of passing every comparison
    bad = [f"{names[j]} rel. error {rel[j]:.3g} > {cfg.tol:g}" for j in range(k) if not rel[j] <= cfg.tol]
    failures.extend(bad)
    if not np.isfinite(image_err):
        failures.append("a re-rendered image holds NaN or inf")
    return VerifyReport(cfg.folder, chosen, names, rel.tolist(), worst.tolist(), image_err, files, cfg.tol, failures,
                        repaired=repaired, compared=compared)
