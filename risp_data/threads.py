"""Thread counts for CPU-heavy work, set by each command itself (docs/PERFORMANCE.md, "Threads").

Why: on a shared 2-core machine torch's default (one intra-op thread per core) oversubscribes the cores
as soon as DataLoader workers or other jobs run beside it; OpenMP's spinning threads then wait for each
other and a training step took 1.6 s instead of 0.16 s with one thread (docs/PERFORMANCE.md). The default
is therefore a fixed function of the CPUs this process may use, never of the momentary load, so that a
run's arithmetic (and its bitwise resume) does not depend on what else the machine was doing.
"""

from __future__ import annotations

import contextlib
import os
from typing import Iterator


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask; ``os.cpu_count()`` where that is unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def default_torch_threads(workers: int = 0, processes: int = 1) -> int:
    """Intra-op threads for each of ``processes`` compute processes that share the machine with
    ``workers`` single-threaded helper processes each (data loaders): the CPUs left over, at least 1."""
    return max(1, (available_cpus() - max(0, workers) * max(1, processes)) // max(1, processes))


def set_torch_threads(threads: int | None, *, workers: int = 0, processes: int = 1) -> int:
    """Set torch's intra-op thread count to ``threads`` (``None`` or 0: the default above); return it."""
    import torch

    if threads is not None and threads < 0:
        from .errors import RispError

        raise RispError(f"--threads must be >= 0 (0: automatic), got {threads}")
    n = threads or default_torch_threads(workers, processes)
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


def set_drjit_threads(threads: int | None) -> int:
    """Set Dr.Jit's CPU (LLVM) worker threads to ``threads`` (``None`` or 0: the CPUs this process may use); return
    it.  Call it once Mitsuba is set up (:func:`risp_data.mitsuba_setup.init_mitsuba`: the libLLVM check must come
    before drjit is first imported).  Reverse-mode renders sum gradients with atomics whose order follows the
    threads, so their last bits depend on this count: tasks record it in result.json."""
    import drjit as dr

    if threads is not None and threads < 0:
        from .errors import RispError

        raise RispError(f"--render-threads must be >= 0 (0: automatic), got {threads}")
    n = threads or available_cpus()
    dr.set_thread_count(n)
    return n


@contextlib.contextmanager
def _count_set_to(get, set_, n: int) -> Iterator[None]:
    """Run the block with a thread count ``set_(n)``, then restore ``get()``'s value from before (also on error)."""
    before = get()
    set_(n)
    try:
        yield
    finally:
        set_(before)


def drjit_threads(n: int):
    """Run the block with ``n`` Dr.Jit CPU threads, then restore the previous count (also on error); Mitsuba must
    be set up first (:func:`set_drjit_threads`)."""
    import drjit as dr

    return _count_set_to(dr.thread_count, dr.set_thread_count, n)


def torch_threads(n: int):
    """Run the block with ``n`` torch intra-op threads, then restore the previous count (also on error)."""
    import torch

    return _count_set_to(torch.get_num_threads, torch.set_num_threads, n)
