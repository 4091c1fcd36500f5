"""Ray, the optional engine that fans work out over machines (``pip install 'risp[ray]'``).

Both users of Ray (``risp-data render --executor ray`` and ``risp-task table --executor ray``) import it
through :func:`require_ray` and wrap their ``ray.get`` calls in :func:`ray_errors`: a task that fails on a
worker reaches the caller as a ``RayTaskError`` whose text is the worker's whole traceback, and the
project's rule is one line per error.
"""

from __future__ import annotations

import re
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


_RAISED = re.compile(r"^[A-Za-z_][\w.]*(Error|Exception|Interrupt|Exit): \S")


def first_line(error: BaseException) -> str:
    """The message of a failed Ray task on one line: its cause's (the exception the task raised, which
    ``RayTaskError.cause`` holds) when it has one.  Without a cause (an actor whose constructor raised,
    ``ActorDiedError``) the text embeds the creation task's traceback: its last ``SomeError: message`` line is the
    error itself.  Otherwise the first non-empty line."""
    cause = getattr(error, "cause", None)
    if isinstance(cause, BaseException):
        error = cause
    lines = [part.strip() for part in str(error).splitlines() if part.strip()]
    if not isinstance(cause, BaseException):
        raised = [line for line in lines if _RAISED.match(line)]
        if raised:
            return raised[-1]
    return lines[0] if lines else type(error).__name__


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
