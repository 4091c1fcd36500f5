"""Find a libLLVM that Dr.Jit's LLVM backend can drive, before ``import mitsuba``.

drjit 1.5 refuses LLVM 14 and aborts the whole process on LLVM 15 (``LLVM ERROR: Cannot select``),
and machines often carry those next to a good one (see docs/install.md).  We therefore point
``DRJIT_LIBLLVM_PATH`` at the newest acceptable library we can find, and fail with one clear line when
there is none.  Nothing happens at import time: call :func:`ensure_llvm` (``risp_data.mitsuba_setup``
does it for you).
"""

from __future__ import annotations

import glob
import os
import re
import subprocess

from .errors import RispError

MIN_MAJOR = 16  # 14 is refused, 15 aborts; 16+ are accepted by drjit 1.5 (19 measured here)
MIN_PLAUSIBLE_MAJOR = 3  # a smaller number in a library name is a soname ABI version, not LLVM's major
_SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib",
    "/usr/lib64",
    "/usr/local/lib",
    "/opt/homebrew/opt/llvm/lib",
    "/usr/local/opt/llvm/lib",
)
INSTALL_HINT = "install one with `apt-get install libllvm19` (or run scripts/setup.sh)"


def _major(path: str) -> int | None:
    """LLVM major version from a library path (libLLVM.so.19.1, libLLVM-19.so, libLLVM.19.dylib,
    /usr/lib/llvm-19/lib/libLLVM.so.1), or None when the path does not tell."""
    name = os.path.basename(path)
    major = None
    m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", name)
    if m:
        major = int(m.group(1))
    else:
        m = re.search(r"libLLVM\.(\d+)", name)  # macOS: libLLVM.19.dylib
        major = int(m.group(1)) if m else None
    if major is None or major < MIN_PLAUSIBLE_MAJOR:  # e.g. libLLVM.so.1: an ABI number, not a version
        m = re.search(r"llvm-(\d+)", path)  # Debian: /usr/lib/llvm-19/lib/libLLVM.so.1
        major = int(m.group(1)) if m else None
    return major


def candidate_libraries() -> list[str]:
    """All libLLVM shared libraries visible through ldconfig or in the usual folders, newest first."""
    found: set[str] = set()
    try:
        out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True, timeout=10).stdout
        for line in out.splitlines():
            if "libLLVM" in line and "=>" in line:
                found.add(line.split("=>")[-1].strip())
    except (OSError, subprocess.SubprocessError):
        pass
    for d in _SEARCH_DIRS:
        found.update(glob.glob(os.path.join(d, "libLLVM*.so*")))
        found.update(glob.glob(os.path.join(d, "libLLVM*.dylib")))
    usable = [p for p in found if os.path.exists(p) and _major(p) is not None]
    return sorted(usable, key=lambda p: (_major(p), len(p)), reverse=True)


def ensure_llvm() -> str:
    """Set ``DRJIT_LIBLLVM_PATH`` to a usable libLLVM (major >= 16) and return its path.

    Respects a ``DRJIT_LIBLLVM_PATH`` the user already set, as long as the file exists and its name does
    not give a major version below MIN_MAJOR (a name without a version is trusted).
    Raises :class:`RispError` with one line when no usable library is found.
    """
    preset = os.environ.get("DRJIT_LIBLLVM_PATH")
    if preset:
        if not os.path.exists(preset):
            raise RispError(f"DRJIT_LIBLLVM_PATH={preset} does not exist; unset it or {INSTALL_HINT}")
        major = _major(preset)
        if major is not None and major < MIN_MAJOR:
            raise RispError(
                f"DRJIT_LIBLLVM_PATH={preset} is LLVM {major}, but Dr.Jit needs LLVM >= {MIN_MAJOR}; "
                f"unset it or {INSTALL_HINT}"
            )
        return preset
    cands = candidate_libraries()
    good = [p for p in cands if _major(p) >= MIN_MAJOR]
    if not good:
        seen = ", ".join(sorted({f"LLVM {_major(p)}" for p in cands})) or "none"
        raise RispError(
            f"no libLLVM >= {MIN_MAJOR} found for Dr.Jit's CPU backend (found: {seen}); {INSTALL_HINT}"
        )
    os.environ["DRJIT_LIBLLVM_PATH"] = good[0]
    return good[0]
