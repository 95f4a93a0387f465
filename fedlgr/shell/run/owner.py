"""One live process per run: its owner holds a ``flock`` on ``owner.lock`` in its checkpoint folder,
which the kernel drops however it dies, so a second ``--resume`` of a live run is refused."""

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
    """Become ``run_id``'s owner (``folder``: its checkpoint folder, created if needed), or raise
    :class:`RunOwned` naming the live owner; nothing if this process holds it already."""
    path = folder / NAME
    if path in _held:
        return
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)  # its checkpoints: private
    except OSError as err:
        raise FedlgrError(f"run {run_id}: {unusable(folder, err)}") from None
    # the process's lock, not a thread's; no soft marker where flock is missing: it outlives a kill
    lock = FileLock(
        path, blocking=False, thread_local=False, fallback_to_soft=False, on_acquired=_sign
    )
    try:
        # a planted link refused here too: filelock opens it O_NOFOLLOW but does not promise to
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
        with open(os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC), errors="replace") as f:
            return f.read(200).split()
    except OSError:
        return []


def release(folder: Path | None) -> None:
    """Give up the run in ``folder`` (nothing if this process does not hold it)."""
    if folder is None:
        return
    lock = _held.pop(folder / NAME, None)
    if lock is not None:
        lock.release()
