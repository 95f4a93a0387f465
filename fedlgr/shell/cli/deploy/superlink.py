"""``fedlgr deploy superlink``: Flower's SuperLink (the server; it runs the ServerApp) behind
fedlgr's Fleet-only gateway, or alone with all its APIs (``--expose-control-api``)."""

from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path
from typing import Annotated

import typer

from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.paths import not_a_file, not_a_folder
from fedlgr.shell.cli.deploy import launch
from fedlgr.shell.cli.verb import Verbs
from fedlgr.shell.signals import terminate_as_interrupt

SUPERLINK_PORT = 9092  # ours, for the Fleet, Control and ServerAppIo APIs (Flower's: 8000)

EXPOSED_CONTROL_WARNING = """\
fedlgr: ####################### WARNING: --expose-control-api #######################
fedlgr: Flower serves ALL its APIs on this port, not only the robots' Fleet API: anyone
fedlgr: who reaches it (ca.pem is public) can register a SuperNode key with flwr
fedlgr: supernode register (then join as a robot) and submit runs with flwr run - code
fedlgr: that runs on this server. Firewall the port to trusted machines, or drop the
fedlgr: option (the default: the Fleet API alone there, the Control API on 127.0.0.1).
fedlgr: ############################################################################"""


app = Verbs()


@app.command("superlink", short_help="start the SuperLink (the server; runs the ServerApp)")
def superlink(
    certs: Annotated[
        Path | None, typer.Option(metavar="DIR", help="from fedlgr deploy certs")
    ] = None,
    host: Annotated[
        str, typer.Option(help="address to listen on (0.0.0.0: every interface)")
    ] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="the robots' port")] = SUPERLINK_PORT,
    internal_port: Annotated[
        int | None,
        typer.Option(
            metavar="PORT",
            help="Flower's own port on 127.0.0.1, for flwr on this machine (default: --port + 1)",
        ),
    ] = None,
    expose_control_api: Annotated[
        bool,
        typer.Option(
            help="no gateway: Flower itself on --host/--port with ALL its APIs, so anyone who "
            "reaches the port can register keys and submit runs (firewalled networks only)",
        ),
    ] = False,
    cold_apps: Annotated[
        bool,
        typer.Option(
            help="start each ServerApp as Flower does, a new process per run (~10 s of "
            "imports before round 1); by default they are forked from a process that has "
            "imported them",
        ),
    ] = False,
    database: Annotated[
        Path | None,
        typer.Option(
            metavar="FILE",
            help="keep registered keys and runs in this SQLite file (default: in memory)",
        ),
    ] = None,
    insecure: launch.Insecure = False,
    print_command: launch.PrintCommand = False,
) -> int:
    """Start flower-superlink on 127.0.0.1:--internal-port (TLS from --certs, SuperNode
    authentication, no installation of dependencies at run time) and serve the robots'
    --host/--port with fedlgr's gateway (fedlgr.shell.deploy.gateway), which passes on
    Flower's Fleet API only: flwr run and flwr supernode register work from this machine
    only. With --expose-control-api, Flower alone on --host/--port with all its APIs."""
    from fedlgr.shell.deploy.credentials import is_host  # lazy: cryptography

    exe = launch.flower_command("flower-superlink")
    if not is_host(host):  # checked here, or Flower would print a bad host as a URL
        raise FedlgrError(
            f"--host {host!r}: not an address to listen on (an IP address such as "
            "0.0.0.0 or 127.0.0.1, or this machine's host name)"
        )
    tls = None if insecure else _tls_files(certs)
    cmd = [str(exe), *_security(tls), "--disable-runtime-dependency-installation"]
    make = not print_command  # the database file: made 0600 unless only printing
    if expose_control_api:
        if internal_port is not None:
            raise FedlgrError("--internal-port is the gateway's: drop it or --expose-control-api")
        print(EXPOSED_CONTROL_WARNING, file=sys.stderr, flush=True)
        cmd += ["--host", host, "--port", str(port), *_database(database, make)]
        return launch.exec_flower(cmd, print_command, insecure)
    internal = _internal_port(port, internal_port)
    cmd += ["--host", "127.0.0.1", "--port", str(internal), *_database(database, make)]
    executor = None
    if not cold_apps:  # its ServerApps forked from a warm process (flower/executor.py)
        cmd += ["--isolation", "process"]
        executor = [sys.executable, "-m", "fedlgr.shell.deploy.flower.executor", "--preload"]
        executor += ["serverapp", "--runtime-api-address", f"127.0.0.1:{internal}"]
        executor += ["--insecure"] if tls is None else ["--root-certificates", str(tls[0])]
    if insecure:
        launch.warn_insecure()
    return _gateway(cmd, host, port, internal, tls, executor, print_command)


def _tls_files(certs: Path | None) -> tuple[Path, Path, Path]:
    """``--certs``' ca.pem, server.pem and server.key, checked."""
    # lazy: cryptography
    from fedlgr.shell.deploy.credentials import check_private_mode, warn_if_open

    if certs is None:
        raise FedlgrError("--certs DIR is required (fedlgr deploy certs DIR), or --insecure")
    folder = launch.absolute(certs)  # a FIFO is named as such, not as a folder without ca.pem
    if why := not_a_folder(folder):
        raise FedlgrError(f"--certs {folder}: {why} (made by fedlgr deploy certs DIR)")
    tls = tuple(
        launch.existing(certs / name, "--certs", "fedlgr deploy certs DIR")
        for name in ("ca.pem", "server.pem", "server.key")
    )
    check_private_mode(tls[2], "--certs")
    # as node-key and the SuperNode warn of theirs: the key's folder should be private too
    warn_if_open(folder, "the certificates or server.key")
    return tls


def _security(tls: tuple[Path, Path, Path] | None) -> list[str]:
    """Flower's TLS and SuperNode-authentication flags, or ``--insecure`` without files."""
    if tls is None:
        return ["--insecure"]
    names = ("--ssl-ca-certfile", "--ssl-certfile", "--ssl-keyfile")
    flags = [text for pair in zip(names, map(str, tls), strict=True) for text in pair]
    return [*flags, "--enable-supernode-auth"]


def _internal_port(port: int, internal_port: int | None) -> int:
    """Flower's own port on 127.0.0.1 behind the gateway: ``--internal-port``, else --port + 1."""
    internal = port + 1 if internal_port is None else internal_port
    for option, number in (("--port", port), ("--internal-port", internal)):
        if not 1 <= number <= 65535:
            raise FedlgrError(f"{option} {number}: a port is 1 to 65535")
    if internal == port:
        raise FedlgrError(f"--internal-port {internal}: must differ from --port (the robots')")
    return internal


def _database(database: Path | None, make: bool = True) -> list[str]:
    """``--database FILE`` for Flower, its folder checked first: Flower would end in a
    SQLAlchemy traceback ("unable to open database file")."""
    if database is None:
        return []
    path = launch.absolute(database)
    if path.is_dir():
        raise FedlgrError(f"--database {path}: a folder; name the SuperLink's database file")
    if why := not_a_file(path):  # a link that loops, say, which Flower would be given as is
        raise FedlgrError(f"--database {path}: {why}")
    if not path.parent.is_dir():
        raise FedlgrError(f"--database {path}: no folder {path.parent} (make it first)")
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise FedlgrError(f"--database {path}: cannot write in {path.parent}")
    # Every run's config and the fleet's state: 0600 whatever the umask, made so before Flower
    # opens it (SQLite gives its journal, -wal and -shm files the database file's mode).
    if make:
        for end in ("", "-journal", "-wal", "-shm"):
            if (file := path.with_name(path.name + end)).exists():
                file.chmod(0o600)
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW, 0o600))
    return ["--database", str(path)]


def _gateway(
    cmd: list[str],
    host: str,
    port: int,
    internal: int,
    tls: tuple[Path, ...] | None,
    executor: list[str] | None,
    print_command: bool,
) -> int:
    """Print what ``superlink`` runs, then run Flower's ``cmd`` behind the gateway."""
    from fedlgr.shell.deploy import gateway  # lazy: httpx, uvicorn and starlette

    files = None if tls is None else gateway.Tls(*tls)
    if files is not None and not gateway.covers_loopback(files.cert):
        raise FedlgrError(
            f"--certs: {files.cert} does not name 127.0.0.1, where the gateway and Flower's "
            "own processes reach the SuperLink: make the certificates again with --host "
            "127.0.0.1 besides the robots' names (fedlgr deploy certs DIR --host NAME --host "
            "127.0.0.1)"
        )
    scheme = "http" if files is None else "https"
    flwr = ["--insecure"] if files is None else ["--ca", str(files.ca)]
    connect = ["fedlgr", "deploy", "connect", "NAME", "--superlink", f"127.0.0.1:{internal}"]
    print(shlex.join(cmd))
    if executor is not None:
        print(shlex.join(executor))
    print(
        f"fedlgr: the robots' port {scheme}://{host}:{port} is fedlgr's gateway: "
        f"POST /v1/fleet/<name> forwarded to {scheme}://127.0.0.1:{internal}, the rest "
        "refused (403)"
    )
    print(
        "fedlgr: flwr run and flwr supernode register work from this machine only: "
        + shlex.join([*connect, *flwr]),
        flush=True,
    )
    if print_command:
        return 0
    with terminate_as_interrupt():  # SIGTERM (systemd, docker stop) stops Flower too
        env = launch.flower_env(Path(cmd[0]))
        return gateway.run(cmd, env, host, port, internal, files, executor)
