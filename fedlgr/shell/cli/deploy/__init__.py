"""``fedlgr deploy certs | node-key | app | connect | superlink | supernode | run``: fedlgr on
Flower's Deployment Runtime (docs/deployment.md).

``certs`` and ``node-key`` write the credentials (:mod:`.credentials`), ``app`` and
``connect`` tell the ``flwr`` command where fedlgr's app and the SuperLink are
(:mod:`.connect`), ``superlink`` and ``supernode`` replace themselves with Flower's processes
(TLS and SuperNode authentication on unless ``--insecure``), and ``run`` submits fedlgr's app
with ``flwr run`` and exits 0 only if the run completed. Each prints the Flower command it
runs; ``--print-command`` prints it and stops there. Each sub-verb's module declares its
options next to its function; what they share is in :mod:`.options` and :mod:`.launch`.
"""

from __future__ import annotations

from fedlgr.shell.cli.deploy import connect, credentials, run, superlink, supernode
from fedlgr.shell.cli.parser import Verbs

SUB_VERBS = (credentials, connect, superlink, supernode, run)  # in the order --help lists them


def add_parser(verbs: Verbs) -> None:
    deploy = verbs.add_parser(
        "deploy",
        help="run on real robots with Flower: credentials, SuperLink, SuperNodes, runs",
        description="fedlgr on Flower's Deployment Runtime: a SuperLink on a server, a "
        "SuperNode on each robot, runs submitted with flwr run (docs/deployment.md).",
    )
    subs = deploy.add_subparsers(dest="deploy_verb", metavar="VERB", required=True)
    for sub_verb in SUB_VERBS:
        sub_verb.add_parser(subs)
