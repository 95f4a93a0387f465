"""The arguments of ``fedlgr deploy`` and its sub-verbs (argparse only, so that ``fedlgr
--help`` stays fast); the sub-verbs themselves are in :mod:`fedlgr.shell.cli.deploy`."""

from __future__ import annotations

from pathlib import Path

SUPERLINK_PORT = 9092  # ours, for the Fleet, Control and ServerAppIo APIs (Flower's: 8000)
SUPERNODE_PORT = 9094  # the SuperNode's local API; one per SuperNode on a machine


def add_parser(verbs) -> None:
    """The ``deploy`` verb and its sub-verbs (called by :func:`fedlgr.shell.cli.build_parser`)."""
    deploy = verbs.add_parser(
        "deploy",
        help="run on real robots with Flower: credentials, SuperLink, SuperNodes, runs",
        description="fedlgr on Flower's Deployment Runtime: a SuperLink on a server, a "
        "SuperNode on each robot, runs submitted with flwr run (docs/deployment.md).",
    )
    subs = deploy.add_subparsers(dest="deploy_verb", metavar="VERB", required=True)

    def sub(name: str, summary: str, func: str, description: str | None = None):
        parser = subs.add_parser(name, help=summary, description=description or summary)
        parser.set_defaults(run=f"fedlgr.shell.cli.deploy:{func}")
        return parser

    def insecure(parser) -> None:
        parser.add_argument(
            "--insecure", action="store_true", help="no TLS, no authentication: test machines only"
        )

    def print_command(parser) -> None:
        parser.add_argument(
            "--print-command", action="store_true", help="print Flower's command line and stop"
        )

    certs = sub(
        "certs",
        "write a CA and the SuperLink's TLS certificate",
        "certs",
        "Write ca.pem, ca.key, server.pem and server.key to DIR. ca.pem goes to every robot "
        "and to whoever runs flwr; server.pem and server.key stay on the SuperLink's machine; "
        "keep ca.key offline.",
    )
    certs.add_argument("dir", type=Path, metavar="DIR", help="folder to write the four files to")
    certs.add_argument(
        "--host",
        action="append",
        metavar="NAME_OR_IP",
        help="a DNS name or address robots use to reach the SuperLink (repeat for several; "
        "default: localhost, 127.0.0.1, ::1)",
    )
    certs.add_argument("--days", type=int, default=365, help="validity (default %(default)s)")
    certs.add_argument(
        "--force",
        action="store_true",
        help="replace the four files in DIR (a symbolic link there is refused all the same)",
    )

    key = sub(
        "node-key",
        "write a robot's SuperNode key pair (DIR/NAME and DIR/NAME.pub)",
        "node_key",
        "Write DIR/NAME (private: to that robot only) and DIR/NAME.pub (registered with "
        "flwr supernode register), and add the robot with its client slot and public key to "
        "the roster DIR/roster.yaml (a Flower run's deploy.roster).",
    )
    key.add_argument("dir", type=Path, metavar="DIR", help="folder to write the key pair to")
    key.add_argument("name", metavar="NAME", help="the robot's name, e.g. robot0")
    key.add_argument(
        "--force",
        action="store_true",
        help="replace an existing key pair (a symbolic link there is refused all the same)",
    )
    key.add_argument(
        "--client",
        type=int,
        metavar="K",
        help="the robot's client slot on the roster DIR/roster.yaml (default: its slot if "
        "NAME is there, else the lowest free one)",
    )
    key.add_argument(
        "--no-roster",
        action="store_true",
        help="do not add the robot to DIR/roster.yaml (its SuperNode then takes part in no run)",
    )

    sub("app", "print the folder of fedlgr's Flower app (for flwr run)", "app")

    connect = sub(
        "connect",
        "point the flwr command at a SuperLink ([superlink.NAME] in $FLWR_HOME/config.toml)",
        "connect",
    )
    connect.add_argument("name", metavar="NAME", help="the connection's name, e.g. robots")
    connect.add_argument(
        "--superlink", required=True, metavar="HOST:PORT", help="the SuperLink's control API"
    )
    connect.add_argument("--ca", type=Path, metavar="CA.pem", help="the deployment's ca.pem")
    connect.add_argument("--default", action="store_true", help="make it flwr's default")
    insecure(connect)

    link = sub(
        "superlink",
        "start the SuperLink (the server; runs the ServerApp)",
        "superlink",
        "Start flower-superlink on 127.0.0.1:--internal-port (TLS from --certs, SuperNode "
        "authentication, no installation of dependencies at run time) and serve the robots' "
        "--host/--port with fedlgr's gateway, which passes on Flower's Fleet API only: flwr "
        "run and flwr supernode register work from this machine only.",
    )
    link.add_argument("--certs", type=Path, metavar="DIR", help="from fedlgr deploy certs")
    link.add_argument(
        "--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every interface)"
    )
    link.add_argument(
        "--port", type=int, default=SUPERLINK_PORT, help="the robots' port (default %(default)s)"
    )
    link.add_argument(
        "--internal-port",
        type=int,
        metavar="PORT",
        help="Flower's own port on 127.0.0.1, for flwr on this machine (default: --port + 1)",
    )
    link.add_argument(
        "--expose-control-api",
        action="store_true",
        help="no gateway: Flower itself on --host/--port with ALL its APIs, so anyone who "
        "reaches the port can register keys and submit runs (firewalled networks only)",
    )
    link.add_argument(
        "--cold-apps",
        action="store_true",
        help="start each ServerApp as Flower does, a new process per run (~10 s of imports "
        "before round 1); by default they are forked from a process that has imported them",
    )
    link.add_argument(
        "--database",
        type=Path,
        metavar="FILE",
        help="keep registered keys and runs in this SQLite file (default: in memory)",
    )
    insecure(link)
    print_command(link)

    node = sub(
        "supernode",
        "start a robot's SuperNode (runs the ClientApp on its data)",
        "supernode",
        "Replace this process with flower-supernode, connected to the SuperLink over TLS with "
        "the robot's registered key; the ClientApp reads the robot's data folder.",
    )
    node.add_argument(
        "--superlink", required=True, metavar="HOST:PORT", help="the SuperLink's fleet API"
    )
    node.add_argument("--ca", type=Path, metavar="CA.pem", help="the deployment's ca.pem")
    node.add_argument("--key", type=Path, metavar="KEY", help="the robot's private node key")
    node.add_argument("--data", type=Path, required=True, metavar="DIR", help="MANNERS-DB layout")
    node.add_argument(
        "--own-data",
        action="store_true",
        help="the robot's own data: all of --data is its shard, split into its own train and "
        "test scenes by data.seed (default: --data holds the whole dataset and the robot "
        "takes its slot's shard of it, as in fedlgr run - for reproducing a simulation)",
    )
    node.add_argument(
        "--client",
        type=int,
        metavar="K",
        help="the client slot this robot expects; the roster decides, and a run whose roster "
        "gives its key another slot is refused by the robot (default: whatever the roster says)",
    )
    node.add_argument("--state-dir", type=Path, metavar="DIR", help="private state between runs")
    node.add_argument("--cache-dir", type=Path, metavar="DIR", help="decoded-image cache")
    node.add_argument(
        "--weights",
        type=Path,
        metavar="FILE",
        help="this robot's copy of the root weights file, for runs whose model.weights is a "
        "file (a robot never reads a path the server names)",
    )
    node.add_argument("--threads", type=int, metavar="N", help="torch threads")
    node.add_argument(
        "--max-retries", type=int, metavar="N", help="give up after N failed connections"
    )
    node.add_argument(
        "--max-wait-time", type=float, metavar="S", help="give up after S seconds of trying"
    )
    node.add_argument(
        "--idle-s",
        type=float,
        metavar="S",
        help="the robot service (which keeps data and models loaded between messages) "
        "leaves after S seconds without a message (default 900)",
    )
    node.add_argument(
        "--poll-s",
        type=float,
        default=0.5,
        metavar="S",
        help="how often an idle robot asks the SuperLink for work, 0.05 to 3 (default "
        "%(default)s; Flower's own is 3, which every round waited out)",
    )
    node.add_argument(
        "--heartbeat-s",
        type=float,
        default=30.0,
        metavar="S",
        help="the heartbeat interval this robot declares, 10 to 1800 (default %(default)g, "
        "Flower's): the SuperLink declares a silent robot lost, and takes back its key from a "
        "restarted SuperNode, after two intervals",
    )
    node.add_argument(
        "--cold-apps",
        action="store_true",
        help="start each ClientApp as Flower does, a new process per message (~3 s each); by "
        "default they are forked from a process that has imported them",
    )
    node.add_argument(
        "--port", type=int, default=SUPERNODE_PORT, help="its local API (default %(default)s)"
    )
    insecure(node)
    print_command(node)

    run = sub(
        "run",
        "submit a run with flwr run, stream its log and exit 0 only if it completed",
        "run",
        "Run fedlgr's app on the SuperLink: CONFIG (made absolute) must exist at that path on "
        "the SuperLink's machine; key=value overrides as in fedlgr run.",
    )
    run.add_argument("config", metavar="CONFIG", help="the config file (as in fedlgr run)")
    run.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")
    run.add_argument(
        "--federation",
        metavar="NAME",
        help="the SuperLink connection (fedlgr deploy connect NAME; default: flwr's default)",
    )
    run.add_argument(
        "--resume",
        nargs="?",
        const="latest",
        metavar="RUN_ID",
        help="continue an interrupted Flower run (its MLflow id; default: the latest "
        "unfinished run of this config) from its newest checkpoint, in the same MLflow run",
    )
    print_command(run)
