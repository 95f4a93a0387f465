"""``fedlgr deploy app`` and ``fedlgr deploy connect``: what the ``flwr`` command needs to
submit a run, fedlgr's Flower app and the SuperLink (a ``[superlink.NAME]`` entry in
``$FLWR_HOME/config.toml``)."""

from __future__ import annotations

import re
from typing import Annotated

import tomli_w
import typer

from fedlgr.errors import FedlgrError
from fedlgr.shell.cli.deploy import launch
from fedlgr.shell.cli.verb import Verbs
from fedlgr.shell.deploy.flower import APP_DIR

app = Verbs()


@app.command("app", short_help="print the folder of fedlgr's Flower app (for flwr run)")
def show_app() -> None:
    """Print the folder of fedlgr's Flower app (for flwr run)."""
    print(APP_DIR)


@app.command(
    "connect",
    short_help="point the flwr command at a SuperLink ([superlink.NAME] in $FLWR_HOME/config.toml)",
)
def connect(
    name: Annotated[str, typer.Argument(metavar="NAME")],
    superlink: Annotated[
        str, typer.Option(metavar="HOST:PORT", help="the SuperLink's control API")
    ],
    ca: launch.Ca = None,
    default: Annotated[bool, typer.Option(help="make it flwr's default")] = False,
    insecure: launch.Insecure = False,
) -> None:
    """Point the flwr command at a SuperLink: NAME (e.g. robots) becomes [superlink.NAME]
    in $FLWR_HOME/config.toml."""
    if not re.fullmatch(r"[A-Za-z0-9_-]+", name):
        raise FedlgrError(f"connection NAME {name!r}: letters, digits, '_', '-' only")
    launch.address(superlink)
    entry = {"address": superlink}
    if insecure:
        launch.no_ca(ca)
        launch.warn_insecure()
        entry["insecure"] = True
    else:
        entry["root-certificates"] = str(launch.certificates(ca))
    path, config = launch.flower_config()
    links = config.setdefault("superlink", {})
    links[name] = entry
    if default or "default" not in links:
        links["default"] = name
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".toml.partial")
    partial.write_text(tomli_w.dumps(config))
    partial.replace(path)
    print(f"wrote [superlink.{name}] (address {superlink}) to {path}")
    if links["default"] != name:
        print(
            f"the default stays {links['default']!r}: use --federation {name} "
            "(or connect again with --default)"
        )
