"""What the ``fedlgr deploy`` sub-verbs share on their command line: the ``--insecure``,
``--print-command`` and ``--ca`` options, and the checks of the paths and addresses they
are given, made before Flower starts (Flower would fail later, or in a traceback)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer

from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.paths import not_a_file, not_a_folder

Insecure = Annotated[
    bool,
    typer.Option("--insecure", help="no TLS, no authentication: test machines only"),
]
PrintCommand = Annotated[
    bool, typer.Option("--print-command", help="print Flower's command line and stop")
]
Ca = Annotated[Path | None, typer.Option(metavar="CA.pem", help="the deployment's ca.pem")]


def absolute(path: Path | str) -> Path:
    return Path(os.path.abspath(os.path.expanduser(path)))


def existing(path: Path | None, option: str, maker: str) -> Path:
    """``option``'s file, which ``maker`` wrote: absolute, and a file that exists."""
    if path is None:
        raise FedlgrError(f"{option} is required (made by {maker}), or --insecure")
    path = absolute(path)
    if why := not_a_file(path):
        raise FedlgrError(f"{option}: {path} is {why} (made by {maker})")
    if not path.is_file():
        raise FedlgrError(f"{option}: {path} does not exist (made by {maker})")
    return path


def certificates(path: Path | None) -> Path:
    """``--ca``: an existing file of PEM certificates."""
    from fedlgr.shell.deploy.credentials import check_certificates  # lazy: cryptography

    path = existing(path, "--ca", "fedlgr deploy certs")
    check_certificates(path)
    return path


def no_ca(ca: Path | None) -> None:
    if ca is not None:
        raise FedlgrError("--insecure turns TLS off: drop --ca (or drop --insecure)")


def address(given: str) -> None:
    """``--superlink HOST:PORT``."""
    host, _, port = given.rpartition(":")
    if not host or not port.isdigit():
        raise FedlgrError(f"--superlink {given!r}: expected HOST:PORT, e.g. 10.0.0.5:9092")
    if not 1 <= int(port) <= 65535:
        raise FedlgrError(f"--superlink {given!r}: a port is 1 to 65535")


def own_folder(folder: Path, option: str, make: bool) -> Path:
    """A folder the robot writes (``--state-dir``, ``--cache-dir``), checked before Flower
    starts, which would take ``/proc/x`` or a key's file: one it can write in, or make (without
    ``make``, made and removed, as only trying tells: root may not write in /proc)."""
    path = absolute(folder)
    if why := not_a_folder(path):  # a file there is named as such, not as "cannot make it"
        raise FedlgrError(f"{option} {path}: {why}")
    if not path.exists():
        above = next(p for p in path.parents if p.exists())
        if not above.is_dir():
            raise FedlgrError(f"{option} {path}: {above} is a file, not a folder")
        made = [p for p in (path, *path.parents) if not p.exists()]  # the deepest first
        try:
            path.mkdir(parents=True)
        except OSError as err:
            raise FedlgrError(f"{option} {path}: cannot make it ({err.strerror})") from None
        if not make:
            for part in made:
                part.rmdir()
            path = above  # what must be writable
    if not os.access(path, os.W_OK | os.X_OK):
        raise FedlgrError(f"{option} {absolute(folder)}: cannot write in {path}")
    return absolute(folder)
