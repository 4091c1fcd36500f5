"""Pick and set the Mitsuba variant: ``cuda_ad_rgb`` on a usable GPU, else ``llvm_ad_rgb``.

Always call :func:`init_mitsuba` before touching ``mitsuba``: it first points Dr.Jit at a usable
libLLVM (:func:`risp_data.llvm.ensure_llvm`), then imports Mitsuba lazily.  Nothing happens at import.
"""

from __future__ import annotations

from .errors import RispError, message_line
from .llvm import ensure_llvm

VARIANTS: tuple[str, ...] = ("llvm_ad_rgb", "cuda_ad_rgb")
_CHOSEN: str | None = None


def _cuda_driver_present() -> bool:
    """True when the CUDA driver library (libcuda) is installed; cheap, imports nothing."""
    import ctypes.util

    return ctypes.util.find_library("cuda") is not None


def _cuda_problem() -> str | None:
    """None when Dr.Jit can drive a CUDA device, else why not: its own error's first line, or that it found none."""
    try:
        import drjit as dr

        return None if dr.has_backend(dr.JitBackend.CUDA) else "none was found"
    except Exception as e:  # noqa: BLE001 - any failure means "no GPU"; its words go into the explicit request's error
        return f"{type(e).__name__}: {message_line(e)}"


def _cuda_usable() -> bool:
    """True when Dr.Jit can drive a CUDA device (no exception, at least one device)."""
    return _cuda_problem() is None


def init_mitsuba(variant: str | None = None) -> str:
    """Set the Mitsuba variant and return its name (idempotent).

    ``variant=None`` picks ``cuda_ad_rgb`` when a CUDA GPU is usable, else ``llvm_ad_rgb``; an explicit
    variant wins.  Unknown or unavailable variants raise :class:`RispError`.  A libLLVM is needed only for
    ``llvm_ad_rgb``: a GPU machine without one renders with ``cuda_ad_rgb``.
    """
    global _CHOSEN
    if variant is not None and variant not in VARIANTS:
        raise RispError(f"unknown Mitsuba variant {variant!r}; choose one of: {', '.join(VARIANTS)}")
    if variant is None and _CHOSEN is not None:
        return _CHOSEN
    try:
        ensure_llvm()
        llvm_error = None
    except RispError as e:
        # a GPU machine may have no libLLVM at all: only llvm_ad_rgb needs it.  Without a CUDA driver, fail before
        # Dr.Jit is imported (its own attempt to load the missing library would print lines of its own)
        if variant == "llvm_ad_rgb" or (variant is None and not _cuda_driver_present()):
            raise
        llvm_error = e
    import mitsuba as mi

    if variant is None:
        if _cuda_usable():
            variant = "cuda_ad_rgb"
        elif llvm_error is not None:
            raise llvm_error
        else:
            variant = "llvm_ad_rgb"
    problem = _cuda_problem() if variant == "cuda_ad_rgb" else None
    if problem is not None:  # asked for by name: say what Dr.Jit said, not only that no GPU was usable
        raise RispError(f"variant 'cuda_ad_rgb' needs a usable CUDA GPU; {problem} (use llvm_ad_rgb)")
    if mi.variant() != variant:
        try:
            mi.set_variant(variant)
        except Exception as e:  # noqa: BLE001 - mitsuba raises plain exceptions
            raise RispError(f"cannot set Mitsuba variant {variant!r}: {e}") from None
    _CHOSEN = variant
    return variant
