"""What the verb modules share: :class:`Verb`, the command typer makes of a verb's function,
and the options of several verbs. Typer and click only, so that ``fedlgr --help`` stays fast."""

from __future__ import annotations

from typing import Annotated

import click
import typer
import typer.core

# Click's own help layout, which typer keeps without rich: with rich installed, typer 0.20
# writes "[default: 1]" as "\[default: 1]" in it, and imports rich to do so.
typer.core.HAS_RICH = False


class Verb(typer.core.TyperCommand):
    """A verb's command (``@app.command(NAME)`` of a :class:`Verbs` app): invoking it hands its
    parsed context back, for :func:`fedlgr.shell.cli.main` to call within its checks. Its
    ``--resume`` may come without a RUN_ID (True): click's options can leave their value out."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        for i, p in enumerate(self.params):
            if isinstance(p, click.Option) and p.is_bool_flag:
                p.secondary_opts = []  # a flag is --NAME alone, not --NAME/--no-NAME
            if p.name == "resume":  # bare (True) or with a value
                opts = {"is_flag": False, "flag_value": True, "type": click.UNPROCESSED}
                self.params[i] = click.Option(p.opts, metavar=p.metavar, help=p.help, **opts)

    def invoke(self, ctx: click.Context) -> click.Context:
        return ctx


class Verbs(typer.Typer):
    """A verb module's typer app: its commands are :class:`Verb`\\ s."""

    def command(self, name: str, **kwargs):
        return super().command(name, cls=Verb, **kwargs)


def parse_crop(text: str) -> tuple[int | None, ...]:
    """``--crop 295,,1313,`` -> (295, None, 1313, None)."""
    parts = text.split(",")
    if len(parts) != 4:
        raise typer.BadParameter("expected LEFT,TOP,RIGHT,BOTTOM (leave one empty for an edge)")
    try:
        return tuple(int(p) if p.strip() else None for p in parts)
    except ValueError as err:
        raise typer.BadParameter(f"not a pixel position: {err}") from None


Overrides = Annotated[list[str], typer.Argument(metavar="[key=value]...")]
TrackingUri = Annotated[
    str | None,
    typer.Option(
        help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or sqlite:///mlflow.db with "
        "artifacts in mlruns/)"
    ),
]
Crop = Annotated[
    tuple | None,
    typer.Option(
        parser=parse_crop, metavar="L,T,R,B", help="LEFT,TOP,RIGHT,BOTTOM before resizing"
    ),
]
