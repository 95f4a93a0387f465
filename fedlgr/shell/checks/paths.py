"""What is at a path a user gave, said before anything opens it (pathlib's ``exists()`` is False for
a dangling link): a link that loops or leads nowhere, a file or a folder where the other goes."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from fedlgr.core.data.columns import CSV_NAME
from fedlgr.errors import DataError


def broken_link(path) -> str | None:
    """Why ``path`` leads nowhere though a symbolic link names it ("a symbolic link that loops", on
    the way to it too, or "a symbolic link to TARGET, which does not exist"), else None."""
    try:
        os.stat(path)
    except OSError as err:
        if err.errno == errno.ELOOP:
            return "a symbolic link that loops"
        if os.path.islink(path):
            return f"a symbolic link to {os.readlink(path)}, which does not exist"
        if err.errno == errno.ENOENT:  # a folder above it may be a dangling link
            return _above(path, links_only=True)
    return None


def _above(path, links_only: bool = False) -> str | None:
    """Why the nearest thing above ``path`` that is there cannot hold it: a dangling symbolic link
    or, unless ``links_only``, a file; None when it is a folder."""
    for parent in Path(path).parents:
        if not os.path.lexists(parent):
            continue
        if os.path.isdir(parent):
            return None
        if os.path.islink(parent) and not os.path.exists(parent):
            return f"under {parent}, a symbolic link to {os.readlink(parent)}, which does not exist"
        if links_only:
            return None
        kind = "a file" if os.path.isfile(parent) else "a device, pipe or socket"
        return f"under {parent}, {kind}, not a folder"
    return None


def _mode(path) -> tuple[str | None, int | None]:
    """``(why, None)`` where ``path`` leads nowhere or something above it is in the way (``why``
    None when nothing is there), else ``(None, its mode)``."""
    try:
        return None, os.stat(path).st_mode
    except OSError:
        return broken_link(path) or _above(path), None


def not_a_file(path) -> str | None:
    """Why ``path`` cannot be read or written as a regular file though something is there: a broken
    link, "a folder", or a device, pipe or socket (which sqlite or ``open()`` would block on or read
    as empty); None for a regular file or nothing there."""
    why, mode = _mode(path)
    if mode is None or stat.S_ISREG(mode):
        return why
    return "a folder" if stat.S_ISDIR(mode) else "not a regular file (a device, pipe or socket)"


def not_a_folder(path) -> str | None:
    """Why ``path`` cannot be (or be made) a folder: a broken link (which ``mkdir`` follows or calls
    "File exists"), or a file, device, pipe or socket; None for a folder or nothing there."""
    why, mode = _mode(path)
    if mode is None or stat.S_ISDIR(mode):
        return why
    kind = "a file" if stat.S_ISREG(mode) else "a device, pipe or socket"
    there = f" ({os.path.realpath(path)})" if os.path.islink(path) else ""
    return f"{kind}{there}, not a folder"


def check_data_path(path: Path | str) -> None:
    """``data.path`` must be a folder: said at once (a run checks it before importing
    torch) rather than as a missing ratings CSV inside a folder that is not there."""
    path = Path(path)
    if path.is_file():  # the CSV would be read and then the images looked for under it
        hint = f"; here data.path={path.parent}" if path.name == CSV_NAME else ""
        raise DataError(
            f"data.path={path} is a file; expected the dataset folder (the one holding "
            f"{CSV_NAME} and images/{hint})"
        )
    # a link, a FIFO or /dev/null is named as such at once, not as a missing folder or CSV
    if why := not_a_folder(path):
        raise DataError(f"data.path={path}: {why}")
    if not path.exists():
        raise DataError(
            f"data.path={path}: no such folder (give the dataset folder, the one holding "
            "the ratings CSV and images/; fedlgr data synth --out FOLDER writes one)"
        )
