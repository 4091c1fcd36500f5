"""PNG files that say where they come from: matplotlib figures and images written atomically
(:func:`risp_data.atomic.atomic_write`), with PNG text chunks naming the software and the seed of the run that made
them — the same seed its JSON beside it records (docs/formats.md §PNG provenance).  Read them back with
:func:`png_provenance` (or PIL: ``Image.open(path).text``)."""

from __future__ import annotations

import os

#: PNG text keys; "Software" is a registered PNG keyword, the others are risp's own
SOFTWARE, SEED, WHAT = "Software", "risp:seed", "risp:what"


def png_text(seed: int | None, what: str | None = None) -> dict[str, str]:
    """The text chunks of a risp PNG: ``Software`` "risp", the run's seed (when it has one), what the file shows."""
    text = {SOFTWARE: "risp"}
    if seed is not None:
        text[SEED] = str(int(seed))
    if what:
        text[WHAT] = what
    return text


def subplots(*args, figsize=None, **kwargs):
    """``(figure, axes)`` as ``pyplot.subplots`` gives them, but on a bare :class:`matplotlib.figure.Figure`: no
    pyplot, no backend switched (a notebook's backend stays its own), nothing to close (docs/formats.md
    §PNG provenance)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    return fig, fig.subplots(*args, **kwargs)


def save_figure(fig, path: "str | os.PathLike", *, seed: int | None, what: str | None = None, dpi: int = 110,
                tight: bool = False) -> None:
    """Write a matplotlib figure to ``path`` as PNG, atomically, its provenance in its text chunks."""
    from .atomic import atomic_write

    with atomic_write(path, "wb", suffix=".png") as f:
        fig.savefig(f, format="png", dpi=dpi, bbox_inches="tight" if tight else None, metadata=png_text(seed, what))


def save_image(image, path: "str | os.PathLike", *, seed: int | None, what: str | None = None) -> None:
    """Write a PIL image to ``path`` as PNG, atomically, its provenance in its text chunks."""
    from PIL.PngImagePlugin import PngInfo

    from .atomic import atomic_write

    info = PngInfo()
    for key, value in png_text(seed, what).items():
        info.add_text(key, value)
    with atomic_write(path, "wb", suffix=".png") as f:
        image.save(f, format="PNG", pnginfo=info)


def png_provenance(path: "str | os.PathLike") -> dict[str, str]:
    """The text chunks of a PNG (``{}`` for one without)."""
    from PIL import Image

    with Image.open(path) as im:
        return dict(getattr(im, "text", {}) or {})
