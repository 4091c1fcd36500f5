"""Registry of environments: one place that data, training and tasks look names up in.

    >>> from risp_data.envs import get_environment, ENV_NAMES
    >>> env = get_environment("cube")

Unknown names raise :class:`risp_data.errors.RispError` listing the valid ones.  Environment modules
are imported lazily (no work at import time), and so is :mod:`.base` (torch) behind ``Camera``, ``Environment``
and ``Mesh``: the command-line tools read ``ENV_NAMES`` for their ``--env`` choices, and their ``--help`` should
not wait a second for torch.
"""

from __future__ import annotations

import importlib

from ..errors import RispError

ENV_NAMES: tuple[str, ...] = ("quadrotor", "cube", "hand", "rod")
_CACHE: dict[str, "Environment"] = {}
_LAZY = ("Camera", "Environment", "Mesh")  # defined in .base, which imports torch


def __getattr__(name: str):
    """``from risp_data.envs import Camera`` (PEP 562): import :mod:`.base` on first use."""
    if name in _LAZY:
        from . import base

        return getattr(base, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def get_environment(name: str) -> Environment:
    """Return the :class:`Environment` called ``name`` (one of :data:`ENV_NAMES`)."""
    if name not in ENV_NAMES:
        raise RispError(f"unknown environment {name!r}; choose one of: {', '.join(ENV_NAMES)}")
    if name not in _CACHE:
        module = importlib.import_module(f"{__name__}.{name}")
        _CACHE[name] = module.make_environment()
    return _CACHE[name]


__all__ = ["ENV_NAMES", "Camera", "Environment", "Mesh", "get_environment"]
