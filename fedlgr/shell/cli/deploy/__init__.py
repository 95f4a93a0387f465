"""``fedlgr deploy certs | node-key | app | connect | superlink | supernode | run``: fedlgr on
Flower's Deployment Runtime (docs/deployment.md); each prints the Flower command it runs."""

from __future__ import annotations

import typer

from fedlgr.shell.cli.deploy import connect, credentials, run, superlink, supernode

SUB_VERBS = (credentials, connect, superlink, supernode, run)  # in the order --help lists them

app = typer.Typer(
    name="deploy",
    short_help="run on real robots with Flower: credentials, SuperLink, SuperNodes, runs",
    help="fedlgr on Flower's Deployment Runtime: a SuperLink on a server, a SuperNode on "
    "each robot, runs submitted with flwr run (docs/deployment.md).",
)
for module in SUB_VERBS:
    app.add_typer(module.app)  # nameless: its commands join deploy's
