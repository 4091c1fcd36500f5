"""Write a file so that readers see either the old file or the complete new one, never half of it."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import tempfile
from typing import IO, Iterator


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_write(path: "str | os.PathLike", mode: str = "wb", suffix: str = "",
                 exclusive: bool = False) -> Iterator[IO]:
    """Yield a file in ``path``'s folder under a temporary name (``.tmp-*``); on success flush, fsync and
    rename it over ``path``; on any exception (including KeyboardInterrupt) remove it and re-raise.
    ``exclusive``: never replace — FileExistsError when something is at ``path`` by then (another process may
    have written it since the caller looked: the check and the publication are one step, a hard link)."""
    folder = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(), suffix=suffix, dir=folder)
    except OSError as e:  # name the file being written, not a temporary name the user never chose
        blocker = file_in_the_way(folder)
        if blocker:  # makedirs says "File exists" of a file where a folder must go: say which and why
            raise NotADirectoryError(errno.ENOTDIR, f"{blocker} is a file, not a folder", os.fspath(path)) from None
        raise OSError(e.errno, e.strerror or str(e), os.fspath(path)) from None
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the file the usual permissions
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        if exclusive:
            _publish_exclusive(tmp, os.fspath(path))
        else:
            os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(e, OSError) and (not e.filename or e.filename == tmp):
            # a failed write (disk full) names no file, a failed rename (a folder where the file goes) the
            # temporary: name the file being written
            raise OSError(e.errno, e.strerror or str(e), os.fspath(path)) from None
        raise


def _publish_exclusive(tmp: str, path: str) -> None:
    """Give the finished ``tmp`` the name ``path`` unless ``path`` exists (FileExistsError naming it)."""
    try:
        os.link(tmp, path)  # fails if path exists, atomically
    except FileExistsError:
        raise FileExistsError(errno.EEXIST, "exists", path) from None
    except OSError:  # a file system without hard links: check, then rename (a narrow race remains there)
        if os.path.lexists(path):
            raise FileExistsError(errno.EEXIST, "exists", path) from None
        os.replace(tmp, path)
        return
    os.unlink(tmp)


TEMP_PREFIX = ".tmp-"


def _host() -> str:
    """This machine's name as it goes into a temporary's name: letters, digits and ``_`` only (``-`` ends the
    owner field, ``@`` separates it)."""
    import socket

    return re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname()) or "host"


def temp_prefix() -> str:
    """``.tmp-<pid>@<host>-``: a temporary names the process that writes it, so that a cleanup elsewhere can tell a
    killed job's leftovers from a running job's work in progress (:func:`remove_temporaries`)."""
    return f"{TEMP_PREFIX}{os.getpid()}@{_host()}-"


_OWNER = re.compile(re.escape(TEMP_PREFIX) + r"(\d+)@([A-Za-z0-9_]+)-")


def temporary_in_use(name: str) -> bool:
    """True when the temporary ``name`` may belong to a job that is still running: its writer's process is alive
    on this machine, or it was written on another machine (whose processes cannot be asked; shared file systems).
    Names without an owner (written before temporaries carried one) are a killed job's."""
    m = _OWNER.match(name)
    if m is None:
        return False
    if m.group(2) != _host():
        return True
    try:
        os.kill(int(m.group(1)), 0)  # signal 0: asks whether the process exists, sends nothing
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    except (OverflowError, ValueError):
        return False
    return True


def file_in_the_way(folder: str) -> str | None:
    """The nearest existing ancestor of ``folder`` (itself included) when it is a file, else None."""
    p = os.path.abspath(folder)
    while not os.path.exists(p) and os.path.dirname(p) != p:
        p = os.path.dirname(p)
    return p if os.path.exists(p) and not os.path.isdir(p) else None


def probe_writable(folder: "str | os.PathLike") -> None:
    """Create ``folder`` (and its parents) and a temporary file in it, then delete the file: an OSError naming what
    failed if files cannot be written there (permissions, a read-only file system, a file in the way)."""
    os.makedirs(folder, exist_ok=True)
    fd, probe = tempfile.mkstemp(prefix=temp_prefix() + "write-check-", dir=folder)
    os.close(fd)
    os.unlink(probe)


def check_writable(folder: "str | os.PathLike", what: str = "output folder") -> None:
    """Raise one RispError line now — not after minutes of work — when ``folder`` could not be created or written
    into: a file in its path, or no write permission on it or on the nearest folder above it that exists.
    Nothing is created (a command refused later for bad input leaves no empty folder)."""
    from .errors import RispError

    path = os.path.abspath(folder)
    probe = path
    while not os.path.exists(probe) and os.path.dirname(probe) != probe:
        probe = os.path.dirname(probe)
    if not os.path.isdir(probe):
        raise RispError(f"{what} {os.fspath(folder)} cannot be made: {probe} is a file")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise RispError(f"{what} {os.fspath(folder)} cannot be written: no write permission on {probe}")


def temp_folder(parent: "str | os.PathLike") -> str:
    """A new empty folder ``parent/.tmp-*`` with the usual permissions (mkdtemp makes 0700), to fill and then
    rename into place."""
    tmp = tempfile.mkdtemp(prefix=temp_prefix(), dir=parent)
    os.chmod(tmp, 0o777 & ~_umask())
    return tmp


def replace_folder(tmp: "str | os.PathLike", dest: "str | os.PathLike") -> None:
    """Rename the finished folder ``tmp`` (a :func:`temp_folder` beside ``dest``) to ``dest``.  An existing ``dest`` is
    first moved aside to a temporary name and deleted only once the new folder is in place; if the rename fails
    it is put back, so readers find the old folder or the new one, never a mix or nothing."""
    import shutil

    dest = os.fspath(dest)
    moved = False  # tmp moved beside the link's target (the caller cleans up only the original path)
    if os.path.islink(dest):  # a link the user made to the folder: replace the folder it points to, keep the link
        target = os.path.realpath(dest)
        if os.path.dirname(target) != os.path.dirname(os.path.realpath(tmp)):  # rename() cannot cross into it
            beside = temp_folder(os.path.dirname(target))
            os.rmdir(beside)
            shutil.move(os.fspath(tmp), beside)
            tmp, moved = beside, True
        dest = target
    old = None
    if os.path.exists(dest):
        old = temp_folder(os.path.dirname(os.path.abspath(dest)))
        os.rmdir(old)
        os.replace(dest, old)
    try:
        os.replace(tmp, dest)
    except BaseException:
        if old is not None and not os.path.exists(dest):
            os.replace(old, dest)
        if moved:
            shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        try:
            shutil.rmtree(old)
        except OSError as e:  # the new folder is in place: say what is left, do not fail the finished job
            import sys

            print(f"note: the replaced folder's old contents could not be deleted ({e}); remove {old} by hand",
                  file=sys.stderr)


def publish_files(tmp: "str | os.PathLike", dest: "str | os.PathLike", names: "list[str]") -> None:
    """Move the finished files ``names`` from the :func:`temp_folder` ``tmp`` into the folder ``dest`` it lies in, as
    one set (files that share a folder with others, so no folder rename can publish them).  The old files of those
    names are first moved into ``tmp`` — the last name first — then the new ones in — the last name last —: ``dest``
    never holds a mix of old and new, and its last name is there only with all the others (the set's mark).  A kill in
    between leaves part of one set in ``dest`` and the rest in ``tmp``, a temporary that :func:`remove_temporaries`
    drops; a failed rename puts the old set back.  The caller deletes ``tmp``."""
    tmp, dest = os.fspath(tmp), os.fspath(dest)
    old = os.path.join(tmp, ".old")  # the names are taken by the new files
    os.makedirs(old, exist_ok=True)  # exists when a failed publication is tried again
    placed: list[str] = []
    try:  # both loops: a failure (or Ctrl-C) while the old set moves out must put it back too
        for name in reversed(names):
            try:
                os.replace(os.path.join(dest, name), os.path.join(old, name))
            except FileNotFoundError:
                pass
        for name in names:
            os.replace(os.path.join(tmp, name), os.path.join(dest, name))
            placed.append(name)
    except BaseException:
        for name in reversed(placed):  # the new files out again, then the old ones back: the set as it was
            os.replace(os.path.join(dest, name), os.path.join(tmp, name))
        for name in names:
            if os.path.lexists(os.path.join(old, name)):
                os.replace(os.path.join(old, name), os.path.join(dest, name))
        raise


def remove_temporaries(folder: "str | os.PathLike") -> None:
    """Delete the temporaries (``.tmp-*``) a killed job left in ``folder``: the files of :func:`atomic_write` and
    the folders of :func:`temp_folder` (a killed task or make-video whose ``--out`` lies inside ``folder``).  Never
    visible to readers under their final names, safe to drop before a job resumes; a link is removed, not followed.
    A temporary whose writer still runs (:func:`temporary_in_use`: say, a task writing its result folder into a run
    folder that a resumed fit cleans) is left alone."""
    import shutil

    if os.path.isdir(folder):
        for name in os.listdir(folder):
            if name.startswith(TEMP_PREFIX) and not temporary_in_use(name):
                path = os.path.join(folder, name)
                if os.path.isdir(path) and not os.path.islink(path):
                    shutil.rmtree(path)
                else:
                    os.unlink(path)


@contextlib.contextmanager
def folder_lock(folder: "str | os.PathLike", busy: str) -> Iterator[None]:
    """Hold an exclusive lock on ``folder/.lock`` (``flock``; released when the holder exits, also when it is
    killed) so two jobs never write one folder; ``busy``: the error line when another process holds it."""
    import fcntl

    from .errors import RispError

    path = os.path.join(folder, LOCK_FILE)
    # 0o666 less the umask, as every other file: a group-shared folder's lock must open for the whole group
    fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # EWOULDBLOCK: another process holds it
            raise RispError(busy) from None
        except OSError as e:  # ENOLCK, ENOSYS, EINVAL: NFS mounted nolock, Lustre without flock — nobody holds it
            raise RispError(f"cannot lock {path}: {e.strerror or e} (a file system without flock? mount it with "
                            "locking, or write the folder on a local disk)") from None
        yield
    finally:
        os.close(fd)


LOCK_FILE = ".lock"


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` through :func:`atomic_write`."""
    with atomic_write(os.fspath(path), "w") as f:
        f.write(text)
