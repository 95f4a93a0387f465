"""Flower's commands as the ``fedlgr deploy`` sub-verbs run them: found next to this Python,
given their environment, printed, and started in this process's place; the ``flwr``
command's own configuration, and the TOML strings of Flower's ``key=value`` settings."""

from __future__ import annotations

import os
import shlex
import shutil
import sys
import tomllib
from pathlib import Path

from fedlgr.errors import FedlgrError

INSECURE_WARNING = """\
fedlgr: ############################ WARNING: --insecure ############################
fedlgr: No TLS: model updates, configs and metrics travel in clear text.
fedlgr: No SuperNode authentication: any machine that reaches the SuperLink's port can
fedlgr: join as a robot, receive the model and send poisoned updates.
fedlgr: Use this on a trusted test machine only (fedlgr deploy certs / node-key otherwise).
fedlgr: ############################################################################"""


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
    out = []
    for char in value:
        if char == "\\":
            out.append("\\\\")
        elif char == '"' or ord(char) < 0x20 or ord(char) == 0x7F:
            out.append(f"\\u{ord(char):04x}")
        else:
            out.append(char)
    return '"' + "".join(out) + '"'
