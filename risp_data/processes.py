"""Helper processes that end with the process they serve (risp_data.generate's render pool, risp_train's
DataLoader workers, risp-task table's --jobs pool): a pid and its start time name one process, on Linux through
/proc; a pool stopped at once on Ctrl-C."""

from __future__ import annotations

import os
import threading
import time


def proc_stat(pid: int) -> list[str] | None:
    """/proc/<pid>/stat's fields from the state on (field 3; the command name may hold spaces), None if absent."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None


def start_time(pid: int) -> str | None:
    """The process's start time (field 22, clock ticks since boot): with the pid, it names one process."""
    fields = proc_stat(pid)
    return fields[19] if fields is not None and len(fields) > 19 else None


def process_gone(pid: int, started: str | None = None) -> bool:
    """True when process ``pid`` has ended: absent, a zombie (its exit only not yet collected) or, with ``started``,
    a process of another start time that has since been given the same pid."""
    if not os.path.isdir("/proc"):  # no /proc: ask the kernel whether the pid exists
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except OSError:
            pass
        return False
    fields = proc_stat(pid)
    if fields is None or fields[0] in ("Z", "X"):
        return True
    return started is not None and len(fields) > 19 and fields[19] != started


def exit_with(pid: int, started: str | None = None, period: float = 0.5) -> None:
    """End this (helper) process when process ``pid`` (of start time ``started``; read now when None) is gone.

    Killed by a signal, a job cannot stop its helpers: the render pool's workers (forks of the fork server, not the
    job's children) would go on writing shards into a folder that a rerun has since locked (a shard stopped
    half-way has no completion marker, so the next run renders it again), and a DataLoader worker started while
    its parent died never notices (torch's watchdog compares with the parent it saw at start, then already init).
    A watcher thread ends the process within ``period`` seconds."""
    if started is None:
        started = start_time(pid)

    def watch():
        while not process_gone(pid, started):
            time.sleep(period)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-job", daemon=True).start()


def end_pool_workers(pool, grace: float = 5.0) -> None:
    """Stop a ``concurrent.futures.ProcessPoolExecutor``'s workers now instead of waiting for the work already handed
    to them (a shard or a table cell, minutes each; their outputs are atomic files, so a stopped one leaves
    nothing under its final name): SIGTERM, then SIGKILL for one still inside a native call after ``grace``
    seconds.  Cancelling the pending futures alone does not do it: the executor has already queued a few calls
    to each worker, and leaving its ``with`` block waits for them."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for proc in procs:
        proc.terminate()
    deadline = time.monotonic() + grace
    for proc in procs:
        proc.join(max(0.0, deadline - time.monotonic()))
        if proc.is_alive():
            proc.kill()
    pool.shutdown(wait=True, cancel_futures=True)
