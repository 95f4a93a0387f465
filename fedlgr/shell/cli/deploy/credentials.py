"""``fedlgr deploy certs`` and ``fedlgr deploy node-key``: the deployment's credentials (a CA
and the SuperLink's TLS certificate; a robot's SuperNode key pair, put on the roster)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from fedlgr.errors import FedlgrError
from fedlgr.shell.cli.verb import Verbs

if TYPE_CHECKING:
    from fedlgr.shell.deploy.roster import Roster

# NAME and NAME.pub share the folder with the deployment's other files: a robot named after one
# of them (or another robot's public key) would overwrite it, or lose its private key to it.
TAKEN_NAMES = {"roster.yaml", "ca.pem", "ca.key", "server.pem", "server.key"}


app = Verbs()


@app.command("certs", short_help="write a CA and the SuperLink's TLS certificate")
def certs(
    folder: Annotated[Path, typer.Argument(metavar="DIR")],
    host: Annotated[
        list[str] | None,
        typer.Option(
            metavar="NAME_OR_IP",
            help="a DNS name or address robots use to reach the SuperLink (repeat for "
            "several; default: localhost, 127.0.0.1, ::1)",
        ),
    ] = None,
    days: Annotated[int, typer.Option(help="validity, in days")] = 365,
    force: Annotated[
        bool,
        typer.Option(
            help="replace the four files in DIR (a symbolic link there is refused all the same)",
        ),
    ] = False,
) -> None:
    """Write ca.pem, ca.key, server.pem and server.key to DIR. ca.pem goes to every robot
    and to whoever runs flwr; server.pem and server.key stay on the SuperLink's machine;
    keep ca.key offline."""
    # lazy: cryptography
    from fedlgr.shell.deploy.credentials import DEFAULT_HOSTS, make_certificates

    # 127.0.0.1 always: Flower's own processes (SuperExec, the ServerApp) and flwr on the
    # SuperLink's machine reach it there, behind fedlgr's gateway (superlink's --internal-port).
    hosts = tuple(dict.fromkeys([*(host or DEFAULT_HOSTS), "127.0.0.1"]))
    paths = make_certificates(folder, hosts, days=days, force=force)
    print(f"wrote {', '.join(map(str, paths.values()))}")
    print(f"server certificate for {', '.join(hosts)}, valid {days} days")
    print(f"  {paths['ca.pem']}: to every robot and to whoever runs flwr (--ca)")
    print(f"  {paths['server.pem']}, {paths['server.key']}: stay on the SuperLink's machine")
    print(f"  {paths['ca.key']}: keep offline (it signs certificates)")


@app.command(
    "node-key", short_help="write a robot's SuperNode key pair (DIR/NAME and DIR/NAME.pub)"
)
def node_key(
    folder: Annotated[Path, typer.Argument(metavar="DIR")],
    name: Annotated[str, typer.Argument(metavar="NAME")],
    force: Annotated[
        bool,
        typer.Option(
            help="replace an existing key pair (a symbolic link there is refused all the same)",
        ),
    ] = False,
    client: Annotated[
        int | None,
        typer.Option(
            metavar="K",
            help="the robot's client slot on the roster DIR/roster.yaml (default: its slot if "
            "NAME is there, else the lowest free one)",
        ),
    ] = None,
    no_roster: Annotated[
        bool,
        typer.Option(
            help="do not add the robot to DIR/roster.yaml (its SuperNode then takes part in "
            "no run)",
        ),
    ] = False,
) -> None:
    """Write DIR/NAME (the private key of robot NAME, e.g. robot0: to that robot only) and
    DIR/NAME.pub (registered with flwr supernode register), and add the robot with its
    client slot and public key to the roster DIR/roster.yaml (a Flower run's
    deploy.roster)."""
    from fedlgr.shell.deploy.credentials import make_node_key  # lazy: cryptography

    _check_name(name)
    roster = None if no_roster else _roster(folder, name, client)
    if no_roster and client is not None:
        raise FedlgrError("--client K is the robot's slot on the roster: drop --no-roster")
    private, public = make_node_key(folder, name, force=force)
    print(f"wrote {private} (private: to that robot only) and {public}")
    if roster is not None:
        member = roster.add(name, public.read_text(), client)
        print(f"added {member} to {roster.write()}")
    print(f"register it with the SuperLink: flwr supernode register {shlex.quote(str(public))}")


def _check_name(name: str) -> None:
    """A robot's NAME: a file name of its own in the deployment's folder."""
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name):
        raise FedlgrError(f"node-key NAME {name!r}: letters, digits, '.', '_', '-' only")
    if len(name) > 100:  # NAME.pub must fit a file name (255 bytes at most)
        raise FedlgrError(f"node-key NAME {name[:20]}...: at most 100 characters")
    if name in TAKEN_NAMES or name.endswith(".pub"):
        raise FedlgrError(
            f"node-key NAME {name!r}: the name of a file this folder holds (NAME and "
            f"NAME.pub are written beside {', '.join(sorted(TAKEN_NAMES))} and other robots' "
            "NAME.pub); choose another"
        )


def _roster(folder: Path, name: str, client: int | None) -> Roster:
    """The roster in DIR (empty if there is none yet), once ``--client`` is known free."""
    from fedlgr.shell.deploy.roster import ROSTER_NAME, Roster  # lazy: cryptography and yaml

    roster = Roster.read_or_empty(folder / ROSTER_NAME)
    if client is not None and client < 0:
        raise FedlgrError(f"--client {client}: a client slot is 0 or more")
    holders = [m for m in roster.members if m.client == client and m.name != name]
    if client is not None and holders:
        raise FedlgrError(f"--client {client}: {holders[0]} holds that slot in {roster.path}")
    return roster
