"""Helpers shared by the command-line tools: one error line, non-zero exit.

Every command runs inside :meth:`RispGroup.invoke`, which turns the errors a user can act on into one
``Error: …`` line (click's ``ClickException``): :class:`RispError`, operating-system errors (disk full,
permission denied, a path under a file — the message names the file), out-of-memory, and the known
messages of dead worker processes.  Programming errors keep their traceback.
"""

from __future__ import annotations

import errno
import sys

import click

from .errors import RispError, message_line

# ------------------------------------------------------------------------------ known errors → one line


def _os_error_line(e: OSError) -> str:
    """``cannot write runs/x/last.pt: No space left on device`` — the file and the system's reason."""
    reason = e.strerror or str(e) or type(e).__name__
    if e.errno == errno.ENOSPC:
        reason += " (free some space and rerun: finished work is kept and resumed)"
    names = [n for n in (e.filename, e.filename2) if n]
    where = " -> ".join(str(n) for n in names)
    return f"{where}: {reason}" if where else f"{type(e).__name__}: {reason}"


_DATALOADER_DIED = ("a data-loading worker process died unexpectedly (killed, or out of memory); rerun with "
                    "--resume to continue from the last checkpoint, with fewer --workers if memory is short")


def _raised_in(e: BaseException, package_path: str) -> bool:
    """True when ``e`` was raised inside files under ``package_path`` (e.g. ``torch/utils/data``)."""
    tb = e.__traceback__
    while tb is not None:
        if package_path in tb.tb_frame.f_code.co_filename.replace("\\", "/"):
            return True
        tb = tb.tb_next
    return False


def _quiet_worker_signals() -> None:
    """Stop torch's SIGCHLD handler from raising "DataLoader worker … killed" a second time while the
    error line is printed (it fires asynchronously, at any bytecode, once per dead worker)."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)


def _worker_message(text: str) -> str:
    """The original message of an error that torch re-raised from a DataLoader worker.  torch wraps it as
    "Caught <Type> in DataLoader worker process N.\nOriginal Traceback …\n<module.Type>: <message>", i.e. the
    worker's whole traceback in the message; the user's line is the last one, after the type."""
    if not (text.startswith("Caught ") and "Original Traceback" in text):
        return text
    last = text.rstrip().splitlines()[-1]
    head, sep, message = last.partition(": ")
    return message if sep and " " not in head else last


def caused_by_interrupt(e: BaseException) -> bool:
    """True when a Ctrl-C is somewhere in ``e``'s chain of causes and contexts.  A KeyboardInterrupt that
    arrives inside native code (Dr.Jit's loops, Mitsuba's import) comes back wrapped — as ``RuntimeError:
    dr.while_loop(): encountered an exception`` or a SystemError that a RispError then names — and must still
    read as an interrupt (exit 130), not as a failure of the renderer."""
    seen: set[int] = set()
    todo = [e]
    while todo:
        x = todo.pop()
        if x is None or id(x) in seen:
            continue
        seen.add(id(x))
        if isinstance(x, KeyboardInterrupt):
            return True
        todo += [x.__cause__, x.__context__]
    return False


def user_error_line(e: BaseException) -> str | None:
    """The one-line message of an error the user can act on, or None for a programming error."""
    from concurrent.futures.process import BrokenProcessPool

    if isinstance(e, RispError):
        return _worker_message(str(e))
    if isinstance(e, BrokenProcessPool):
        return ("a worker process died unexpectedly (killed, or out of memory); completed shards are kept: "
                "rerun the same command to resume, with fewer --workers or a smaller --res if memory is short")
    if isinstance(e, MemoryError):
        return "out of memory; use a smaller --res or fewer --workers (risp-train: a smaller --batch-size)"
    if isinstance(e, ImportError) and e.name and not e.name.startswith(("risp_data", "risp_train", "risp_tasks")):
        # a dependency missing or broken in this environment (not one of risp's own modules: that is a bug)
        return (f"the library {e.name!r} cannot be imported ({message_line(e, 'ImportError')}): "
                "install risp's dependencies (bash scripts/setup.sh, or pip install -e .)")
    if isinstance(e, (ConnectionError, EOFError)) and _raised_in(e, "torch/utils/data"):
        return _DATALOADER_DIED  # the pipe of a worker killed mid-batch
    if isinstance(e, OSError):
        return _os_error_line(e)
    text = str(e)
    if isinstance(e, RuntimeError) and "DataLoader worker" in text and ("exited unexpectedly" in text
                                                                      or "killed by signal" in text):
        return _DATALOADER_DIED
    return None


def run_cli(group: click.Group, argv: list[str] | None = None) -> None:
    """Run a click group; user errors become ``Error: <message>`` on stderr and exit status 1."""
    try:
        group.main(args=argv, standalone_mode=False)
    except click.exceptions.Abort:  # click's name for a Ctrl-C it caught: the same line as KeyboardInterrupt's
        click.echo("Error: interrupted", err=True)
        sys.exit(130)
    except click.BadParameter as e:
        if isinstance(e, click.MissingParameter):  # a usage error: click's usage lines and status 2
            e.show()
            sys.exit(e.exit_code)
        # an unknown name or a malformed value (--env nosuch): bad input like any other, one line and status 1
        click.echo(f"Error: {' '.join(e.format_message().split())}", err=True)
        sys.exit(1)
    except click.ClickException as e:
        e.show()
        sys.exit(e.exit_code)
    except KeyboardInterrupt:
        click.echo("Error: interrupted", err=True)
        sys.exit(130)
    except Exception as e:
        if caused_by_interrupt(e):
            click.echo("Error: interrupted", err=True)
            sys.exit(130)
        line = user_error_line(e)
        if line is None:
            raise
        _quiet_worker_signals()
        click.echo(f"Error: {line}", err=True)
        sys.exit(1)


class RispGroup(click.Group):
    """A click group whose sub-commands turn user errors (see :func:`user_error_line`) into one error line
    (also under CliRunner and inside the ``risp`` group)."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except click.ClickException:
            raise
        except Exception as e:
            if caused_by_interrupt(e):  # click turns it into Abort: "Error: interrupted", exit 130
                raise KeyboardInterrupt from None
            line = user_error_line(e)
            if line is None:
                raise
            _quiet_worker_signals()
            raise click.ClickException(line) from None
