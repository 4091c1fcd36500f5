"""Pick and set the Mitsuba variant: ``cuda_ad_rgb`` on a usable GPU, else ``llvm_ad_rgb``.

Always call :func:`init_mitsuba` before touching ``mitsuba``: it first points Dr.Jit at a usable
libLLVM (:func:`risp_data.llvm.ensure_llvm`), then imports Mitsuba lazily.  Nothing happens at import.
"""

from __future__ import annotations

from .errors import RispError
from .llvm import ensure_llvm

VARIANTS: tuple[str, ...] = ("llvm_ad_rgb", "cuda_ad_rgb")
_CHOSEN: str | None = None


def _cuda_driver_present() -> bool:
    """True when the CUDA driver library (libcuda) is installed; cheap, imports nothing."""
    import ctypes.util

    return ctypes.util.find_library("cuda") is not None


def _cuda_usable() -> bool:
    """True when Dr.Jit can drive a CUDA device (no exception, at least one device)."""
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # noqa: BLE001 - any failure simply means "no GPU"
        return False


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
    if variant == "cuda_ad_rgb" and not _cuda_usable():
        raise RispError("variant 'cuda_ad_rgb' needs a usable CUDA GPU; none was found (use llvm_ad_rgb)")
    if mi.variant() != variant:
        try:
            mi.set_variant(variant)
        except Exception as e:  # noqa: BLE001 - mitsuba raises plain exceptions
            raise RispError(f"cannot set Mitsuba variant {variant!r}: {e}") from None
    _CHOSEN = variant
    return variant
