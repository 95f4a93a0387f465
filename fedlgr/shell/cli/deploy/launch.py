"""What the ``fedlgr deploy`` sub-verbs share: Flower's commands (found, printed, started in
this process's place), the ``flwr`` configuration, and the options checked before Flower starts."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import sys
import tomllib
from pathlib import Path
from typing import Annotated

import typer

from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.paths import not_a_file, not_a_folder

INSECURE_WARNING = """\
fedlgr: ############################ WARNING: --insecure ############################
fedlgr: No TLS: model updates, configs and metrics travel in clear text.
fedlgr: No SuperNode authentication: any machine that reaches the SuperLink's port can
fedlgr: join as a robot, receive the model and send poisoned updates.
fedlgr: Use this on a trusted test machine only (fedlgr deploy certs / node-key otherwise).
fedlgr: ############################################################################"""

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
            for part in reversed(made):  # private from the first byte, whatever the umask
                part.mkdir(mode=0o700)
        except OSError as err:
            raise FedlgrError(f"{option} {path}: cannot make it ({err.strerror})") from None
        if not make:
            for part in made:
                part.rmdir()
            path = above  # what must be writable
    if not os.access(path, os.W_OK | os.X_OK):
        raise FedlgrError(f"{option} {absolute(folder)}: cannot write in {path}")
    return absolute(folder)


def flower_command(name: str) -> Path:
    """Flower's command ``name``: the one next to this Python (the venv), else on PATH."""
    beside = Path(sys.executable).parent / name
    if beside.is_file() and os.access(beside, os.X_OK):
        return beside
    found = shutil.which(name)
    if found is None:
        raise FedlgrError(
            f"{name} not found next to {sys.executable} nor on PATH: Flower is not installed "
            "in this environment (uv sync installs flwr)"
        )
    return Path(found)


def flower_env(exe: Path) -> dict[str, str]:
    """Flower's processes start flower-superexec (and the apps) from PATH: ``exe``'s folder
    first. Its telemetry and update check are off unless set otherwise."""
    env = {**os.environ, "PATH": f"{exe.parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    env.setdefault("FLWR_TELEMETRY_ENABLED", "0")
    env.setdefault("FLWR_DISABLE_UPDATE_CHECK", "1")  # flwr is pinned (pyproject.toml)
    # How often a SuperExec looks for work: Flower's default of 1 s adds up to 1 s per message.
    env.setdefault("FLWR_SUPEREXEC_TASK_POLL_INTERVAL", "0.2")
    return env


def exec_flower(
    cmd: list[str], print_command: bool, insecure: bool = False, private: bool = False
) -> int:
    """Print ``cmd``, then (unless ``--print-command``) replace this process with it;
    ``private``: what it writes is this user's only (a robot: its state, log, socket, cache)."""
    if insecure:
        warn_insecure()
    print(shlex.join(cmd), flush=True)
    if print_command:
        return 0
    sys.stderr.flush()
    if private:  # files 0600 and folders 0700, whatever the umask
        os.umask(0o077)
    os.execve(cmd[0], cmd, flower_env(Path(cmd[0])))
    return 1  # not reached


def warn_insecure() -> None:
    print(INSECURE_WARNING, file=sys.stderr, flush=True)


def flower_config() -> tuple[Path, dict]:
    """The flwr CLI's ``config.toml`` (under ``$FLWR_HOME``, else ``~/.flwr``) and its
    settings ({} while there is none)."""
    path = Path(os.environ.get("FLWR_HOME") or Path.home() / ".flwr") / "config.toml"
    try:
        return path, tomllib.loads(path.read_text()) if path.is_file() else {}
    except tomllib.TOMLDecodeError as err:
        raise FedlgrError(f"{path}: not valid TOML ({err})") from None
    except OSError as err:
        raise FedlgrError(f"{path}: cannot read it ({err.strerror or err})") from None


def toml_string(value: str) -> str:
    """``value`` as a TOML string for Flower's ``key=value`` settings (``--node-config``,
    ``--run-config``). Flower finds each value with the pattern ``"[^"]*"`` before reading it
    as TOML, so a ``"`` inside is written as the escape ``\\u0022``, never ``\\"``."""
    return '"' + re.sub(r'[\\"\x00-\x1f\x7f]', _escape, value) + '"'


def _escape(char: re.Match) -> str:
    return "\\\\" if char[0] == "\\" else f"\\u{ord(char[0]):04x}"
