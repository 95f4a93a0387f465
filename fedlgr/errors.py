"""User-facing errors.

Anything a user can fix (a bad CSV, a missing image, an impossible setting) raises a
:class:`FedlgrError` whose message names the file, row/stamp, column or setting at fault.
The command line prints such errors as one line and exits non-zero; any other exception
is a bug and keeps its traceback.
"""


class FedlgrError(Exception):
    """An error the user can fix; its message is printed as one line by the CLI."""


class DataError(FedlgrError):
    """Bad input data: CSV content, image files, folder layout."""


class ConfigError(FedlgrError):
    """An impossible or malformed setting."""


def join_problems(subject: str, problems: list[str], shown: int = 5) -> str:
    """One line that names ``subject`` and lists the first ``shown`` problems."""
    if len(problems) == 1:
        return f"{subject}: {problems[0]}"
    listed = "; ".join(problems[:shown])
    more = f"; ... and {len(problems) - shown} more" if len(problems) > shown else ""
    return f"{subject}: {len(problems)} problems: {listed}{more}"


def exception_chain(err: BaseException | None):
    """``err``, then what caused it or was being handled when it was raised, each once."""
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        yield err
        err = err.__cause__ or err.__context__


def interrupt_in(err: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or SIGTERM (:class:`fedlgr.shell.signals.Terminated`) behind ``err``, if any:
    one that arrives while Optuna records a trial turns into Optuna 4's
    ``UnboundLocalError: ... 'updated_state'`` in ``_run_trial``, and a sweep stopped
    there ended in two tracebacks (the seventh fault sweep, i17)."""
    return next((e for e in exception_chain(err) if isinstance(e, KeyboardInterrupt)), None)


def broken_link(path) -> str | None:
    """Why ``path`` leads nowhere though a symbolic link names it, in words - "a symbolic
    link that loops" (on the way to it, too) or "a symbolic link to TARGET, which does not
    exist" - or None. pathlib's ``exists()``/``is_file()`` say False for both, and an
    error that then says "does not exist" or "cannot make it" names the wrong reason."""
    import errno
    import os

    try:
        os.stat(path)
    except OSError as err:
        if err.errno == errno.ELOOP:
            return "a symbolic link that loops"
        if os.path.islink(path):
            return f"a symbolic link to {os.readlink(path)}, which does not exist"
        if err.errno == errno.ENOENT:  # a folder above it may be one (the tenth sweep, d24)
            return _above(path, links_only=True)
    return None


def _above(path, links_only: bool = False) -> str | None:
    """Why the nearest thing above ``path`` that is there cannot hold it: "under DIR, a
    symbolic link to TARGET, which does not exist" (``mkdir(parents=True)`` said "File
    exists", or followed it and made TARGET) or, unless ``links_only``, "under FILE, a file,
    not a folder"; None when it is a folder."""
    import os
    from pathlib import Path

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
    """``(why, None)`` where ``path`` leads nowhere (:func:`broken_link`) or something above
    it is in the way (:func:`_above`; ``why`` None when simply nothing is there), else
    ``(None, its mode)``: what :func:`not_a_file` and :func:`not_a_folder` start from."""
    import os

    if why := broken_link(path):
        return why, None
    try:
        return None, os.stat(path).st_mode
    except OSError:
        return _above(path), None


def not_a_file(path) -> str | None:
    """Why ``path`` cannot be read or written as a regular file though something is there:
    a broken link (:func:`broken_link`), "a folder", or "not a regular file (a device, pipe
    or socket)" - which sqlite or ``open()`` would block on (a FIFO), read as empty
    (/dev/null) or write beside (``/dev/null-journal``, the ninth fault sweep's c06-c17) -
    or None for a regular file or nothing there."""
    import stat

    why, mode = _mode(path)
    if mode is None or stat.S_ISREG(mode):
        return why
    return "a folder" if stat.S_ISDIR(mode) else "not a regular file (a device, pipe or socket)"


def not_a_folder(path) -> str | None:
    """Why ``path`` cannot be (or be made) a folder: a broken link (:func:`broken_link`;
    ``mkdir`` said only "File exists", or followed a dangling one and made its target), or a
    file, device, pipe or socket already there; None for a folder or nothing there."""
    import os
    import stat

    why, mode = _mode(path)
    if mode is None or stat.S_ISDIR(mode):
        return why
    kind = "a file" if stat.S_ISREG(mode) else "a device, pipe or socket"
    there = f" ({os.path.realpath(path)})" if os.path.islink(path) else ""
    return f"{kind}{there}, not a folder"
