"""``risp-data inspect``: a manifest summary and a PNG contact sheet of images and Jacobian images."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .errors import RispError
from .shards import load_manifest
from .shards.layout import channel_map
from .shards.reader import complete_indices, read_samples
from .figures import save_figure


@dataclass(frozen=True)
class InspectConfig:
    folder: str
    png: str | None = None  # default: <folder>/contact_sheet.png
    samples: int = 4
    deep: bool = False  # also hash every shard file (sha256 against the manifest)


def tar_sample_count(path: str) -> int:
    """Samples (distinct keys) a tar yields when read as a stream: a zero-filled tail ends it early."""
    import tarfile

    keys = set()
    try:
        with tarfile.open(path, mode="r:") as tar:
            for member in tar:
                keys.add(member.name.split(".", 1)[0])
    except (tarfile.TarError, OSError):
        return -1
    return len(keys)


def shard_problems(folder: str, m: dict, deep: bool) -> list[str]:
    """Every listed shard checked: files present with the listed sizes, each tar holding the listed number of
    samples, and (``deep``) every file's sha256.  One line per damaged shard."""
    from .shards.manifest import shard_problem
    from .shards.wds import WDS_DIR

    problems = []
    for rec in sorted(m["shards"], key=lambda r: r["index"]):
        why = shard_problem(folder, rec, deep)
        if why is None:
            for rel in rec["files"]:
                if rel.startswith(WDS_DIR + "/"):
                    n = tar_sample_count(os.path.join(folder, rel))
                    if n != rec["stop"] - rec["start"]:
                        why = f"{os.path.join(folder, rel)} holds {n} samples, the manifest lists {rec['stop'] - rec['start']}"
                        break
        if why is not None:
            problems.append(f"shard {rec['index']}: {why}")
    return problems


def integrity_lines(m: dict, problems: list[str], deep: bool) -> list[str]:
    checked = "sizes, sample counts" + (", sha256" if deep else "; --deep also hashes every file")
    n = len(m["shards"])
    lines = [f"integrity    {n - len(problems)}/{n} listed shards intact ({checked})"]
    lines += [f"  DAMAGED    {p}" for p in problems]
    return lines


def _folder_bytes(folder: str) -> int:
    total = 0
    for root, _, files in os.walk(folder):
        total += sum(os.path.getsize(os.path.join(root, f)) for f in files)
    return total


def _storage_line(m: dict) -> str:
    """The Jacobian layout (docs/formats.md): which ψ keep only their own channel, and fall-back samples."""
    if not m["jacobian"]:
        return "none (--no-jacobian)"
    own = {n: c for n, c in channel_map(m).items() if c != "RGB"}
    if not own:
        return "full (all three channels of every psi)"
    fallback = sum(len(r.get("jacobian_fallback", {})) for r in m["shards"])
    return (f"own-channel for {', '.join(f'{n}:{c}' for n, c in own.items())}; "
            f"{fallback} sample(s) kept in full (other channels not exactly 0)")


def summarize(folder: str, m: dict) -> str:
    """Human-readable manifest summary (one fact per line)."""
    # the counts as the shard records give them (the manifest's own "counts"/"complete" are derived from those, and a
    # hand-edited manifest may lack them)
    done = sum(r["stop"] - r["start"] for r in m["shards"])
    c = {"complete_samples": done, "complete_shards": len(m["shards"])}
    complete = len(m["shards"]) == m["num_shards"]
    lines = [
        f"folder       {folder}  ({_folder_bytes(folder) / 2**20:.1f} MiB)",
        f"environment  {m['env']}   domain {m['domain']}   variant {m['variant']}   look {m.get('look', 'unrecorded')}",
        f"images       {m['resolution']}x{m['resolution']}, {m['spp']} spp, jacobian {'yes' if m['jacobian'] else 'no'}",
        f"samples      {c['complete_samples']}/{m['n']} complete in {c['complete_shards']}/{m['num_shards']} shards "
        f"of {m['shard_size']}{'' if complete else '  (INCOMPLETE: rerun render to resume)'}",
        f"formats      {', '.join(m['formats'])}",
        f"J storage    {_storage_line(m)}",
        f"seed         {m['seed']}",
        f"state        {', '.join(m['state_names'])}",
        "psi          name                 nominal      low     high",
    ]
    p = m["psi"]
    for j, name in enumerate(p["names"]):
        lines.append(f"             {name:<18} {p['nominal'][j]:8.3f} {p['low'][j]:8.3f} {p['high'][j]:8.3f}")
    versions = ", ".join(f"{k} {v}" for k, v in sorted(m.get("versions", {}).items()) if v)
    lines.append(f"versions     {versions}")
    lines.append(f"created      {m.get('created', '?')}   updated {m.get('updated', '?')}")
    return "\n".join(lines)


def _tonemap(image: np.ndarray) -> np.ndarray:
    """Linear RGB -> sRGB-ish display values (gamma 2.2, clipped)."""
    return np.clip(np.nan_to_num(image), 0.0, 1.0) ** (1.0 / 2.2)


def contact_sheet(samples: list[dict], psi_names: list[str], path: str, *, seed: int | None) -> str:
    """One row per sample: the image, then ∂I/∂ψ_j per ψ_j (its strongest colour channel), drawn with a
    diverging colormap and symmetric limits ±max|∂I/∂ψ_j| so zero is white."""
    from risp_data.figures import subplots

    cols = 1 + (len(psi_names) if samples[0]["jacobian"] is not None else 0)
    fig, axes = subplots(len(samples), cols, figsize=(1.6 * cols, 1.7 * len(samples)), squeeze=False)
    for r, s in enumerate(samples):
        ax = axes[r, 0]
        ax.imshow(_tonemap(s["image"]), interpolation="nearest")
        ax.set_title(s["key"], fontsize=7)
        if s["jacobian"] is not None:
            for j, name in enumerate(psi_names):
                # the colour channel ψ_j moves most (object_r moves R only: an RGB mean would dilute it)
                c = int(np.argmax(np.nansum(np.abs(s["jacobian"][j]), axis=(0, 1))))
                d = s["jacobian"][j][..., c]
                lim = float(np.nanmax(np.abs(d))) or 1.0
                ax = axes[r, j + 1]
                ax.imshow(d, cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
                ax.set_title(f"∂I_{'RGB'[c]}/∂{name}\n±{lim:.2g}", fontsize=6)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    save_figure(fig, path, seed=seed, what="risp-data inspect: images and Jacobians")
    return path


def inspect_folder(cfg: InspectConfig) -> tuple[str, str | None, list[str]]:
    """Summary text, the contact sheet path (None when no shard is complete yet or a shard is damaged) and
    one line per damaged shard (:func:`shard_problems`)."""
    if cfg.samples <= 0:
        raise RispError(f"--samples must be a positive integer, got {cfg.samples}")
    m = load_manifest(cfg.folder)
    problems = shard_problems(cfg.folder, m, cfg.deep)
    summary = "\n".join([summarize(cfg.folder, m), *integrity_lines(m, problems, cfg.deep)])
    indices = complete_indices(m)
    if not indices or problems:
        return summary, None, problems
    chosen = [indices[int(i)] for i in np.linspace(0, len(indices) - 1, min(cfg.samples, len(indices)))]
    chosen = sorted(set(chosen))
    got = read_samples(cfg.folder, chosen)
    path = cfg.png or os.path.join(cfg.folder, "contact_sheet.png")
    try:
        contact_sheet([got[i] for i in chosen], list(m["psi"]["names"]), path, seed=m.get("seed"))
    except OSError as e:
        raise RispError(f"cannot write contact sheet {path}: {e.strerror or e}") from None
    return summary, path, problems
