"""Registry of environments: one place that data, training and tasks look names up in.

    >>> from risp_data.envs import get_environment, ENV_NAMES
    >>> env = get_environment("cube")

Unknown names raise :class:`risp_data.errors.RispError` listing the valid ones.  Environment modules
are imported lazily (no work at import time).
"""

from __future__ import annotations

import importlib

from ..errors import RispError
from .base import Camera, Environment, Mesh

ENV_NAMES: tuple[str, ...] = ("quadrotor", "cube", "hand", "rod")
_CACHE: dict[str, Environment] = {}


def get_environment(name: str) -> Environment:
    """Return the :class:`Environment` called ``name`` (one of :data:`ENV_NAMES`)."""
    if name not in ENV_NAMES:
        raise RispError(f"unknown environment {name!r}; choose one of: {', '.join(ENV_NAMES)}")
    if name not in _CACHE:
        module = importlib.import_module(f"{__name__}.{name}")
        _CACHE[name] = module.make_environment()
    return _CACHE[name]


__all__ = ["ENV_NAMES", "Camera", "Environment", "Mesh", "get_environment"]
