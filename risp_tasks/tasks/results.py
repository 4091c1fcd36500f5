"""The result folder of a task run (docs/tasks.md §Result folder), written under a temporary name and renamed
when complete, so a folder named like a result is always a complete one."""

from __future__ import annotations

import json
import os
import platform
import shutil

import numpy as np

from risp_data.atomic import check_writable, file_in_the_way, replace_folder, temp_folder
from risp_data.figures import save_figure, save_image
from risp_data.errors import RispError
from risp_data.shards.manifest import risp_commit

from ..strict_json import strict_json


RESULT_FILE = "result.json"


def check_free(out: str, overwrite: bool = False) -> None:
    """``out`` may be written: it does not exist, or (``overwrite``) it is a task's result folder (it holds a
    result.json) — never an arbitrary folder or a file, which --overwrite does not delete."""
    if not os.path.exists(out):
        blocker = file_in_the_way(os.path.dirname(os.path.abspath(out)))  # the result must go under a folder
        if blocker:
            raise RispError(f"{out}: {blocker} is a file, not a folder: choose another --out")
    elif not overwrite:
        raise RispError(f"{out}: result folder exists; choose another --out, remove it, or give --overwrite")
    elif not (os.path.isdir(out) and os.path.isfile(os.path.join(out, RESULT_FILE))):
        raise RispError(f"{out}: exists and is not a task's result folder (no {RESULT_FILE}); --overwrite replaces "
                        f"only those: choose another --out")
    # the folder is written beside out (a temporary sibling renamed into place; through a link, into the folder
    # it names): say now, not after the work
    for parent in {os.path.dirname(os.path.abspath(out)), os.path.dirname(os.path.realpath(out))}:
        check_writable(parent, f"--out {out}: its folder")


def versions() -> dict:
    import drjit
    import mitsuba
    import torch

    out = {"python": platform.python_version(), "torch": torch.__version__, "mitsuba": mitsuba.__version__,
           "drjit": drjit.__version__, "numpy": np.__version__,
           "mitsuba_variant": mitsuba.variant()}  # None when the task rendered nothing (the state loss)
    out["risp_commit"] = risp_commit()
    return out


class ResultFolder:
    """Write files into a temporary sibling folder; ``commit()`` renames it to ``out``."""

    def __init__(self, out: str, overwrite: bool = False):
        check_free(out, overwrite)
        parent = os.path.dirname(os.path.abspath(out))
        os.makedirs(parent, exist_ok=True)
        self.out, self.overwrite = out, overwrite
        self.tmp = temp_folder(parent)

    def path(self, name: str) -> str:
        return os.path.join(self.tmp, name)

    def write_json(self, name: str, data: dict) -> None:
        """Strict JSON (what jq and JavaScript parse): a non-finite number, e.g. the last iterate's loss after a
        diverging final step, is written as null."""
        with open(self.path(name), "w") as f:
            json.dump(strict_json(data), f, indent=1, allow_nan=False)

    def commit(self) -> str:
        """Put the finished folder in place; with ``overwrite`` the old result folder is moved aside first and
        deleted after, so a failure leaves either the old folder or the new one, never a mix."""
        check_free(self.out, self.overwrite)
        replace_folder(self.tmp, self.out)
        return self.out

    def discard(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)


def plot_loss(path: str, history: list[float], title: str, last: float | None = None,
              best: int | None = None, *, seed: int | None) -> None:
    """Loss per iteration (at the variables before that iteration's step), then ``last``: the loss after the last
    step, which the history does not hold; ``best``: the returned iterate's index, marked.  Without iterations the
    figure says so instead of showing empty axes."""
    from risp_data.figures import subplots

    fig, ax = subplots(figsize=(5, 3.2))
    if history:
        # x = the steps taken before the loss was measured (0: the start), the index result.json's best_iteration
        # uses; the point after the last step is x = len(history)
        x = np.arange(len(history))
        ax.semilogy(x, np.maximum(history, 1e-12), marker="o" if len(history) <= 20 else None, ms=3, label="loss")
        if last is not None and np.isfinite(last):
            ax.semilogy([len(history) - 1, len(history)], np.maximum([history[-1], last], 1e-12), "--", color="C0",
                        lw=0.8, label="after the last step")
        if best is not None and best < len(history):
            ax.semilogy([best], [max(history[best], 1e-12)], "*", color="C3", ms=10, label="returned (best)")
        elif best is not None and last is not None and np.isfinite(last):  # the last iterate is the one returned
            ax.semilogy([len(history)], [max(last, 1e-12)], "*", color="C3", ms=10, label="returned (best)")
        ax.legend(fontsize=7)
    else:
        ax.text(0.5, 0.5, "no iterations (--iterations 0):\nthe result is the start", ha="center", va="center",
                transform=ax.transAxes)
    ax.set_xlabel("steps taken (0: the start; result.json's best_iteration)")
    ax.set_ylabel("loss")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, seed=seed, what="risp-task: loss per iteration")


def plot_scan(path: str, scan: dict, final: dict, truth: dict | None = None, *, seed: int | None) -> None:
    """``sysid --init scan``: the state loss over each scanned parameter's grid (one panel per parameter), the
    chosen start, the final estimate and, where known, the truth."""
    from risp_data.figures import subplots

    names = scan["parameters"]
    fig, axes = subplots(1, len(names), figsize=(3.2 * len(names), 2.8), squeeze=False)
    for j, name in enumerate(names):
        ax = axes[0][j]
        grid, loss = np.asarray(scan["grid"][j]), np.asarray(scan["loss"][j], np.float64)
        ax.plot(grid, loss, ".-", lw=1, label="state loss on the grid")
        best = int(np.argmin(loss))
        ax.plot([grid[best]], [loss[best]], "o", color="C1", label="start of the descent")
        ax.axvline(final[name], color="C2", lw=1, label="estimate")
        if truth is not None and name in truth:
            ax.axvline(truth[name], color="k", ls="--", lw=1, label="truth")
        ax.set_xlabel(name, fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0][0].set_ylabel("loss", fontsize=8)
    axes[0][0].legend(fontsize=6)
    fig.suptitle("sysid --init scan" + (" (one pass of coordinate search)" if len(names) > 1 else ""), fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, seed=seed, what="risp-task sysid: the scanned start")


def plot_trajectories(path: str, names, t, curves: dict[str, np.ndarray], *, seed: int | None) -> None:
    """One panel per state component; ``curves``: label -> (T, S) (NaN rows are skipped)."""
    from risp_data.figures import subplots

    n = len(names)
    cols = min(3, n)
    rows = (n + cols - 1) // cols
    fig, axes = subplots(rows, cols, figsize=(3.4 * cols, 2.2 * rows), squeeze=False)
    for i, name in enumerate(names):
        ax = axes[i // cols][i % cols]
        for label, (tt, y) in curves.items():
            ax.plot(tt, y[:, i], ".-" if len(tt) < 30 else "-", label=label, lw=1, ms=3)
        ax.set_title(name, fontsize=8)
        ax.tick_params(labelsize=7)
    for j in range(n, rows * cols):
        axes[j // cols][j % cols].axis("off")
    axes[0][0].legend(fontsize=6)
    axes[-1][0].set_xlabel("time [s]", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, seed=seed, what="risp-task: trajectories", dpi=100)


def save_strip(path: str, rows: dict[str, np.ndarray], note: str | None = None, *, seed: int | None) -> None:
    """PNG: one row per label (reference / initial / optimized), frames side by side, sRGB; ``note``: a line of
    text under the rows (e.g. that the simulated rows are drawn in the nominal look, not the video's)."""
    from PIL import Image, ImageDraw

    from ..video import to_uint8

    label_w = 70
    imgs = {k: to_uint8(v) for k, v in rows.items()}
    h, w = next(iter(imgs.values())).shape[1:3]
    n = max(len(v) for v in imgs.values())
    foot = 14 if note else 0
    canvas = Image.new("RGB", (max(label_w + n * (w + 2), 6 * len(note or "") + 4), len(imgs) * (h + 2) + foot),
                       (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for r, (label, frames) in enumerate(imgs.items()):
        draw.text((2, r * (h + 2) + h // 2 - 5), label, fill=(0, 0, 0))
        for c, img in enumerate(frames):
            canvas.paste(Image.fromarray(img), (label_w + c * (w + 2), r * (h + 2)))
    if note:
        draw.text((2, len(imgs) * (h + 2) + 1), note, fill=(60, 60, 60))
    save_image(canvas, path, seed=seed, what="risp-task: reference / initial / optimized frames")
