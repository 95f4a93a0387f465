"""``fedlgr deploy certs | node-key | app | connect | superlink | supernode | run``: fedlgr on
Flower's Deployment Runtime (docs/deployment.md).

``certs`` and ``node-key`` write the credentials (:mod:`.credentials`), ``app`` and
``connect`` tell the ``flwr`` command where fedlgr's app and the SuperLink are
(:mod:`.connect`), ``superlink`` and ``supernode`` replace themselves with Flower's processes
(TLS and SuperNode authentication on unless ``--insecure``), and ``run`` submits fedlgr's app
with ``flwr run`` and exits 0 only if the run completed. Each prints the Flower command it
runs; ``--print-command`` prints it and stops there. Each sub-verb is a function that
declares its options; what they share is in :mod:`.options` and :mod:`.launch`.
"""

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
