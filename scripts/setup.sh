#!/usr/bin/env bash
# Install everything risp needs on a fresh Debian/Ubuntu-like machine, into ./.venv.
#   - a libLLVM that Dr.Jit's CPU backend accepts (>= 16; drjit 1.5 refuses 14 and aborts on 15)
#   - a Python virtual environment with risp and its dependencies (CPU torch unless a GPU is present)
# Idempotent: a second run only checks (pip runs again only when pyproject.toml changed).
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-python3}
SUDO=""
if [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi

# apt-get waits up to 10 minutes for a package manager that another process holds (e.g. a second set-up
# started at the same time on a fresh machine) instead of failing at once on the dpkg lock.
APT="apt-get -o DPkg::Lock::Timeout=600"

llvm_ok() { "$PY" -c 'import sys; sys.path.insert(0, "."); from risp_data.llvm import ensure_llvm; ensure_llvm()' >/dev/null 2>&1; }

# 1. System library: libLLVM >= 16 (docs/install.md)
if ! llvm_ok; then
  if command -v apt-get >/dev/null 2>&1; then
    echo "[setup] installing libLLVM 19 for Dr.Jit (apt-get)"
    $SUDO $APT update -qq
    $SUDO $APT install -y -qq libllvm19 >/dev/null || $SUDO $APT install -y -qq libllvm18 >/dev/null \
      || $SUDO $APT install -y -qq libllvm17 >/dev/null || $SUDO $APT install -y -qq libllvm16 >/dev/null
  fi
  if ! llvm_ok; then
    "$PY" -c 'import sys; sys.path.insert(0, "."); from risp_data.llvm import ensure_llvm; ensure_llvm()' 2>&1 | tail -n 1 >&2
    echo "error: no usable libLLVM (>= 16) for Dr.Jit; install libllvm19 with your package manager" >&2
    exit 1
  fi
fi

# 2. Python environment
if ! "$PY" -c 'import venv, ensurepip' >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
  $SUDO $APT update -qq && $SUDO $APT install -y -qq python3-venv >/dev/null
fi
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv"
  "$PY" -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null 2>&1 || true  # a new venv's pip may be old
fi
VPY=.venv/bin/python
if ! "$VPY" -c 'import torch' >/dev/null 2>&1; then
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi >/dev/null 2>&1; then
    echo "[setup] installing torch (CUDA build)"
    "$VPY" -m pip install -q "torch>=2.4"
  else
    # The CPU build avoids ~3 GB of CUDA wheels. PyPI has no +cpu versions: try the configured indexes (a local
    # wheel folder may hold the tested one), then PyTorch's own CPU index, then (saying so) the default build.
    echo "[setup] installing torch (CPU build)"
    "$VPY" -m pip install -q "torch==2.13.0+cpu" 2>/dev/null \
      || "$VPY" -m pip install -q --timeout 20 --retries 1 --index-url https://download.pytorch.org/whl/cpu "torch>=2.4" 2>/dev/null \
      || { echo "[setup] no CPU build of torch reachable: installing the default build (with CUDA libraries)"
           "$VPY" -m pip install -q "torch>=2.4"; }
  fi
fi
# A second run skips pip when this checkout's risp is installed from this pyproject.toml (a stamp in .venv): the
# demo and the tests run the set-up every time, and pip's resolve took ~5 s and printed setuptools' banner.
STAMP=.venv/.risp-setup
WANT="$(sha256sum pyproject.toml | cut -d' ' -f1) $(pwd)"
installed() {
  # -I: the checkout's folder is not on sys.path, so this finds what the venv has installed, not ./risp_data
  [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$WANT" ] && [ -x .venv/bin/risp ] \
    && [ "$("$VPY" -I -c 'import os, risp_data; print(os.path.dirname(os.path.dirname(os.path.abspath(risp_data.__file__))))' 2>/dev/null)" = "$(pwd)" ]
}
if installed; then
  echo "[setup] risp is installed (pyproject.toml unchanged since the last set-up)"
else
  echo "[setup] installing risp and its dependencies"
  "$VPY" -m pip install -q -e ".[dev]"
  echo "$WANT" > "$STAMP"
fi
"$VPY" -c 'from risp_data.llvm import ensure_llvm; print("[setup] Dr.Jit will use", ensure_llvm())'
