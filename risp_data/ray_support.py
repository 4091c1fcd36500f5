"""Ray, the optional engine that fans work out over machines (``pip install 'risp[ray]'``).

Both users of Ray (``risp-data render --executor ray`` and ``risp-task table --executor ray``) import it
through :func:`require_ray` and wrap their ``ray.get`` calls in :func:`ray_errors`: a task that fails on a
worker reaches the caller as a ``RayTaskError`` whose text is the worker's whole traceback, and the
project's rule is one line per error.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager

from .errors import RispError


def require_ray():
    """The ``ray`` module, or one error line saying how to install it."""
    try:
        import ray
    except ImportError:
        raise RispError("--executor ray needs the optional ray extra: pip install 'risp[ray]'") from None
    return ray


def first_line(error: BaseException) -> str:
    """The message of a failed Ray task on one line: its cause's (the exception the task raised, which
    ``RayTaskError.cause`` holds) when it has one, else its own; the first non-empty line of that."""
    cause = getattr(error, "cause", None)
    source = cause if isinstance(cause, BaseException) else error
    text = str(source)
    line = next((part.strip() for part in text.splitlines() if part.strip()), "")
    return line or type(source).__name__


@contextmanager
def ray_errors(what: str):
    """Turn a Ray error raised inside the block into ``RispError("<what> failed on Ray: <first line>")``."""
    try:
        yield
    except Exception as error:
        ray = sys.modules.get("ray")
        exceptions = getattr(ray, "exceptions", None)
        if exceptions is None or not isinstance(error, exceptions.RayError):
            raise
        raise RispError(f"{what} failed on Ray: {first_line(error)}") from None
