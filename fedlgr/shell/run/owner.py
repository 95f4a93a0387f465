"""One live process per run: the run's owner holds an exclusive lock on its checkpoint
folder for the run's life.

A run that checkpoints (or is resumed) has one owner: the process that created it, or the
one that resumed it. The owner holds a ``filelock.FileLock`` (``flock`` underneath) on
``<folder>/owner.lock`` from before its first round (before a resume reads the
checkpoint) until the run has ended; the file names its host and pid. The kernel drops
the lock when the process dies, however it dies (SIGKILL included), so a lock that is
held always means a live owner: a second ``--resume`` - at the same moment, or of a run
whose process is stopped (Ctrl-Z, a suspended VM) and whose heartbeat went stale - is
refused in one line that names the owner. Heartbeats stay what they are for: telling a
dead run from a live one on another machine
(:func:`fedlgr.shell.tracking.mlflow_run.dead_reason`).

``flock`` holds across processes on one machine and on the network file systems that
support it (NFSv4, Lustre, CephFS); a checkpoint folder a resumed run reads must be one
every node of the run can reach anyway.
"""

from __future__ import annotations

import errno
import os
import socket
from pathlib import Path

from filelock import FileLock, Timeout

from fedlgr.errors import FedlgrError

NAME = "owner.lock"

_held: dict[Path, FileLock] = {}  # lock file -> this process's lock on it


class RunOwned(FedlgrError):
    """Another live process owns the run."""


def unusable(folder: Path, err: OSError) -> str:
    """Why checkpoints cannot go to ``folder``, and the way out."""
    reason = err.strerror or str(err)
    return (
        f"cannot make the checkpoint folder {folder} ({reason}); name one this user can "
        "write (tracking.checkpoint_dir=...), or tracking.checkpoint=0 for no checkpoints"
    )


def check_folder(folder: Path) -> None:
    """Refuse, before a run starts, a checkpoint root that cannot be made or written."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not os.access(folder, os.W_OK | os.X_OK):
            raise OSError(errno.EACCES, "not writable")
    except OSError as err:
        raise FedlgrError(unusable(folder, err)) from None


def claim(folder: Path, run_id: str) -> None:
    """Become ``run_id``'s owner (``folder``: its checkpoint folder, created if needed), or
    raise :class:`RunOwned` naming the live owner. Claiming a folder this process already
    holds does nothing."""
    path = folder / NAME
    if path in _held:
        return
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise FedlgrError(f"run {run_id}: {unusable(folder, err)}") from None
    # The process's own, not a thread's; no soft marker where flock is missing (it would
    # outlive a killed owner); the owner's host and pid written once the lock is held.
    lock = FileLock(
        path, blocking=False, thread_local=False, fallback_to_soft=False, on_acquired=_sign
    )
    try:
        # A planted link is not a way to make the owner write elsewhere: filelock opens
        # the file O_NOFOLLOW, but does not promise to, so the link is refused here too.
        if path.is_symlink():
            raise OSError(errno.ELOOP, os.strerror(errno.ELOOP))
        lock.acquire()
    except Timeout:
        host, pid = [*_owner(path), "?", "?"][:2]
        raise RunOwned(
            f"run {run_id} is owned by process {pid} on {host}, which is alive (it holds "
            f"{path}); stop that process first (if it is stopped, `kill -CONT {pid}` lets it "
            "finish), or wait until it ends"
        ) from None
    except OSError as err:
        reason = err.strerror or str(err)
        raise FedlgrError(f"run {run_id}: cannot open its lock file {path}: {reason}") from None
    _held[path] = lock


def _sign(fd: int) -> None:
    """Name this process in the lock file it has just locked (``fd``)."""
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{socket.gethostname()} {os.getpid()}\n".encode(), 0)


def _owner(path: Path) -> list[str]:
    """The host and pid the owner wrote in its lock file (none if it cannot be read)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        return []
    try:
        return os.pread(fd, 200, 0).decode(errors="replace").split()
    finally:
        os.close(fd)


def holds(folder: Path) -> bool:
    return folder / NAME in _held


def release(folder: Path | None) -> None:
    """Give up the run in ``folder`` (nothing if this process does not hold it)."""
    if folder is None:
        return
    lock = _held.pop(folder / NAME, None)
    if lock is not None:
        lock.release()


def release_all() -> None:
    for path in list(_held):
        release(path.parent)
