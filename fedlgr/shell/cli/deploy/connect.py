"""``fedlgr deploy app`` and ``fedlgr deploy connect``: what the ``flwr`` command needs to
submit a run, fedlgr's Flower app and the SuperLink (a ``[superlink.NAME]`` entry in
``$FLWR_HOME/config.toml``)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import tomli_w

from fedlgr.errors import FedlgrError
from fedlgr.shell.cli.deploy import launch
from fedlgr.shell.cli.deploy.options import (
    add_insecure,
    add_sub_verb,
    address,
    certificates,
    no_ca,
)
from fedlgr.shell.cli.parser import Verbs
from fedlgr.shell.deploy.flower import APP_DIR


def add_parser(subs: Verbs) -> None:
    add_sub_verb(subs, "app", "print the folder of fedlgr's Flower app (for flwr run)", app)
    parser = add_sub_verb(
        subs,
        "connect",
        "point the flwr command at a SuperLink ([superlink.NAME] in $FLWR_HOME/config.toml)",
        connect,
    )
    parser.add_argument("name", metavar="NAME", help="the connection's name, e.g. robots")
    parser.add_argument(
        "--superlink", required=True, metavar="HOST:PORT", help="the SuperLink's control API"
    )
    parser.add_argument("--ca", type=Path, metavar="CA.pem", help="the deployment's ca.pem")
    parser.add_argument("--default", action="store_true", help="make it flwr's default")
    add_insecure(parser)


def app(args: argparse.Namespace) -> int:
    print(APP_DIR)
    return 0


def connect(args: argparse.Namespace) -> int:
    if not re.fullmatch(r"[A-Za-z0-9_-]+", args.name):
        raise FedlgrError(f"connection NAME {args.name!r}: letters, digits, '_', '-' only")
    address(args.superlink)
    entry = {"address": args.superlink}
    if args.insecure:
        no_ca(args)
        launch.warn_insecure()
        entry["insecure"] = True
    else:
        entry["root-certificates"] = str(certificates(args.ca))
    path, config = launch.flower_config()
    home = path.parent
    links = config.setdefault("superlink", {})
    links[args.name] = entry
    if args.default or "default" not in links:
        links["default"] = args.name
    home.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".toml.partial")
    partial.write_text(tomli_w.dumps(config))
    partial.replace(path)
    print(f"wrote [superlink.{args.name}] (address {args.superlink}) to {path}")
    if links["default"] != args.name:
        print(
            f"the default stays {links['default']!r}: use --federation {args.name} "
            "(or connect again with --default)"
        )
    return 0
