"""``fedlgr deploy supernode``: a robot's SuperNode (it runs the ClientApp on the robot's
data), its options checked here, in one line each, before Flower starts."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Annotated

import typer

from fedlgr.errors import ConfigError, FedlgrError
from fedlgr.shell import config as conf  # its names load when used: pydantic
from fedlgr.shell.checks.paths import not_a_file, not_a_folder
from fedlgr.shell.cli.deploy import launch
from fedlgr.shell.cli.verb import Verbs
from fedlgr.shell.deploy.flower.supernode import HEARTBEAT_RANGE, POLL_RANGE

SUPERNODE_PORT = 9094  # the SuperNode's local API; one per SuperNode on a machine

app = Verbs()

# The options whose help takes several lines, declared here to keep supernode() short.
OwnData = Annotated[
    bool,
    typer.Option(
        help="the robot's own data: all of --data is its shard, split into its own train and "
        "test scenes by data.seed (default: --data holds the whole dataset and the robot "
        "takes its slot's shard of it, as in fedlgr run - for reproducing a simulation)",
    ),
]
Client = Annotated[
    int | None,
    typer.Option(
        metavar="K",
        help="the client slot this robot expects; the roster decides, and a run whose roster "
        "gives its key another slot is refused by the robot (default: whatever the roster "
        "says)",
    ),
]
Weights = Annotated[
    Path | None,
    typer.Option(
        metavar="FILE",
        help="this robot's copy of the root weights file, for runs whose model.weights is a "
        "file (a robot never reads a path the server names)",
    ),
]
IdleS = Annotated[
    float | None,
    typer.Option(
        metavar="S",
        help="the robot service (which keeps data and models loaded between messages) "
        "leaves after S seconds without a message (default 900)",
    ),
]
PollS = Annotated[
    float,
    typer.Option(
        metavar="S",
        help="how often an idle robot asks the SuperLink for work, 0.05 to 3 (Flower's own "
        "is 3, which every round waited out)",
    ),
]
HeartbeatS = Annotated[
    float,
    typer.Option(
        metavar="S",
        help="the heartbeat interval this robot declares, 10 to 1800 (the default is "
        "Flower's): the SuperLink declares a silent robot lost, and takes back its key from a "
        "restarted SuperNode, after two intervals",
    ),
]
ColdApps = Annotated[
    bool,
    typer.Option(
        help="start each ClientApp as Flower does, a new process per message (~3 s each); by "
        "default they are forked from a process that has imported them",
    ),
]


@app.command("supernode", short_help="start a robot's SuperNode (runs the ClientApp on its data)")
def supernode(
    superlink: Annotated[str, typer.Option(metavar="HOST:PORT", help="the SuperLink's fleet API")],
    data: Annotated[Path, typer.Option(metavar="DIR", help="MANNERS-DB layout")],
    ca: launch.Ca = None,
    key: Annotated[
        Path | None, typer.Option(metavar="KEY", help="the robot's private node key")
    ] = None,
    own_data: OwnData = False,
    client: Client = None,
    state_dir: Annotated[
        Path | None, typer.Option(metavar="DIR", help="private state between runs")
    ] = None,
    cache_dir: Annotated[
        Path | None, typer.Option(metavar="DIR", help="decoded-image cache")
    ] = None,
    weights: Weights = None,
    threads: Annotated[int | None, typer.Option(metavar="N", help="torch threads")] = None,
    max_retries: Annotated[
        int | None, typer.Option(metavar="N", help="give up after N failed connections")
    ] = None,
    max_wait_time: Annotated[
        float | None, typer.Option(metavar="S", help="give up after S seconds of trying")
    ] = None,
    idle_s: IdleS = None,
    poll_s: PollS = 0.5,
    heartbeat_s: HeartbeatS = 30.0,
    cold_apps: ColdApps = False,
    port: Annotated[int, typer.Option(help="its local API")] = SUPERNODE_PORT,
    insecure: launch.Insecure = False,
    print_command: launch.PrintCommand = False,
) -> int:
    """Replace this process with flower-supernode, connected to the SuperLink over TLS with
    the robot's registered key; the ClientApp reads the robot's data folder."""
    args = SimpleNamespace(**locals())  # the options, as the steps below read them
    from fedlgr.shell.data.ratings import read_ratings  # lazy: numpy

    launch.flower_command("flower-supernode")  # Flower is installed here
    data = _check_options(args)
    # flower-supernode, its idle poll shortened, its heartbeat as chosen and its ClientApps
    # forked from a warm process (shell/deploy/flower/supernode.py and executor.py say why)
    cmd = [sys.executable, "-m", "fedlgr.shell.deploy.flower.supernode", "--poll-s", str(poll_s)]
    cmd += ["--heartbeat-s", f"{heartbeat_s:g}"]
    if not cold_apps:
        cmd += ["--warm-apps", f"127.0.0.1:{port}"]
    cmd += ["--superlink", superlink, *_credentials(args)]
    # A broken ratings file is found now, in one line, not when the first run's first
    # message reaches the robot (the images are decoded then, at the run's image size).
    read_ratings(data)
    settings = _node_config(args, data)
    cmd += ["--node-config", " ".join(settings), "--host", "127.0.0.1", "--port", str(port)]
    for option, value in (("--max-retries", max_retries), ("--max-wait-time", max_wait_time)):
        if value is not None:
            cmd += [option, str(value)]
    return launch.exec_flower(cmd, print_command, insecure, private=True)


def _check_options(args: SimpleNamespace) -> Path:
    """The options Flower would take as they are, checked; the absolute ``--data`` folder."""
    launch.address(args.superlink)
    if args.client is not None and args.client < 0:
        raise FedlgrError(f"--client {args.client}: a client index is 0 or more")
    if args.threads is not None and not 1 <= args.threads <= conf.MAX_PER_MACHINE:
        raise FedlgrError(
            f"--threads {args.threads}: 1 to {conf.MAX_PER_MACHINE} (runtime.threads' bound)"
        )
    data = launch.absolute(args.data)
    if why := not_a_folder(data):  # a file or a loop there is named, not "no such folder"
        raise FedlgrError(f"--data {data}: {why} (the robot's dataset, MANNERS-DB layout)")
    if not data.is_dir():
        raise FedlgrError(f"--data {data}: no such folder (the robot's dataset, MANNERS-DB layout)")
    for option, value, (low, high) in (
        ("--poll-s", args.poll_s, POLL_RANGE),
        ("--heartbeat-s", args.heartbeat_s, HEARTBEAT_RANGE),
    ):
        if not low <= value <= high:  # NaN too
            raise FedlgrError(f"{option} {value}: must be between {low:g} and {high:g} seconds")
    for option, value in (
        ("--max-retries", args.max_retries),
        ("--max-wait-time", args.max_wait_time),
    ):
        if value is not None and not value >= 0:  # NaN too
            raise FedlgrError(f"{option} {value}: must be 0 or more")
    return data


def _credentials(args: SimpleNamespace) -> list[str]:
    """TLS with the deployment's CA and the robot's node key, or ``--insecure``."""
    if args.insecure:
        launch.no_ca(args.ca)
        if args.key is not None:
            raise FedlgrError(
                "--insecure turns TLS off, and SuperNode authentication needs TLS: drop --key "
                "(or drop --insecure)"
            )
        return ["--insecure"]
    from fedlgr.shell.deploy.credentials import check_node_key  # lazy: cryptography

    cmd = ["--root-certificates", str(launch.certificates(args.ca))]
    key = launch.existing(args.key, "--key", "fedlgr deploy node-key DIR NAME")
    check_node_key(key)
    return [*cmd, "--auth-supernode-private-key", str(key)]


def _node_config(args: SimpleNamespace, data: Path) -> list[str]:
    """The ClientApp's ``key=value`` settings (``--node-config``), its folders made."""
    settings = [f"data-path={launch.toml_string(str(data))}"]
    if args.client is not None:
        settings.append(f"client={args.client}")
    if args.own_data:
        settings.append("own-data=true")
    for name, folder in (("state-dir", args.state_dir), ("cache-dir", args.cache_dir)):
        if folder is not None:
            own = launch.own_folder(folder, f"--{name}", make=not args.print_command)
            settings.append(f"{name}={launch.toml_string(str(own))}")
    if args.weights is not None:
        settings.append(f"weights={launch.toml_string(str(_weights(args.weights)))}")
    if args.threads is not None:
        settings.append(f"threads={args.threads}")
    if args.idle_s is not None:
        if not args.idle_s > 0:
            raise FedlgrError(f"--idle-s {args.idle_s}: must be > 0")
        settings.append(f"robot-idle-s={args.idle_s}")
    return settings


def _weights(given: Path) -> Path:
    """``--weights``: a file holding a model's state dict, checked by its content too, since
    any readable file (a system file, say) would otherwise be taken as the root weights."""
    from fedlgr.core.models.scholar import file_state_dict  # lazy: torch

    weights = launch.absolute(given)
    if why := not_a_file(weights):  # a folder or a loop there is named, not "no such file"
        raise FedlgrError(f"--weights {weights}: {why}")
    if not weights.is_file():
        raise FedlgrError(
            f"--weights {weights}: no such file (this robot's copy of the root weights "
            "a run's model.weights names)"
        )
    try:
        file_state_dict(weights)
    except ConfigError as err:
        said = str(err).replace(f"model.weights={weights}", f"--weights {weights}")
        raise FedlgrError(said) from None
    return weights
