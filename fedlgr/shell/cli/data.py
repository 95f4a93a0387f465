"""``fedlgr data synth | show | check``."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Literal

import typer

from fedlgr.core.data.columns import LABEL_SHORT_NAMES
from fedlgr.shell import config as conf  # its names load when used: pydantic
from fedlgr.shell.cli.verb import Crop, Verbs
from fedlgr.shell.console import Progress, table
from fedlgr.shell.signals import terminate_as_interrupt

app = Verbs(name="data", help="create, inspect and check datasets")
Folder = Annotated[Path, typer.Argument(metavar="FOLDER")]


@app.command("synth", short_help="write a synthetic living room in the MANNERS-DB layout")
def synth(
    out: Annotated[Path, typer.Option(help="folder to write")],
    scenes: Annotated[int, typer.Option(help="scenes to write")] = 1000,
    seed: Annotated[int, typer.Option(help="seed of the scenes and ratings")] = 0,
    size: Annotated[int, typer.Option(help="image width and height in pixels")] = 128,
    force: Annotated[bool, typer.Option(help="overwrite a non-empty folder")] = False,
) -> None:
    """Write a synthetic living room in the MANNERS-DB layout."""
    from fedlgr.shell.data.synth import synthesize  # lazy: PIL and numpy

    # SIGTERM (timeout, Slurm) is a Ctrl-C: synthesize removes what it had written
    with terminate_as_interrupt(), Progress("synthesising", unit="scene") as bar:
        s = synthesize(out, scenes, seed, size, force=force, progress=bar)
    print(
        f"wrote {s.scenes} scenes ({s.circle} circle, {s.arrow} arrow) and {s.ratings} ratings "
        f"to {s.out} in {s.seconds:.1f} s"
    )
    print(
        table(
            ["action", "mean rating"],
            zip(LABEL_SHORT_NAMES, map(float, s.label_means), strict=True),
        )
    )


@app.command("show", short_help="contact sheet of a few scenes with their labels")
def show(
    folder: Folder,
    out: Annotated[Path, typer.Option(help="the PNG file to write")] = Path("contact_sheet.png"),
    scenes: Annotated[int, typer.Option(help="scenes on the sheet")] = 8,
    seed: Annotated[int, typer.Option(help="seed of the choice of scenes")] = 0,
    crop: Crop = None,
) -> None:
    """Contact sheet of a few scenes of FOLDER (a MANNERS-DB-layout folder) with their
    labels."""
    from fedlgr.shell.data.summary import contact_sheet  # lazy: torch and PIL

    print(f"wrote {contact_sheet(folder, out, scenes, seed, crop)}")


@app.command("check", short_help="validate a dataset folder and summarise it")
def check(
    folder: Folder,
    modality: Annotated[
        Literal["image", "features"],
        typer.Option(help="check the images too, or the CSV's descriptors alone"),
    ] = "image",
    size: Annotated[int, typer.Option(help="image width and height to decode to, in pixels")] = 128,
    crop: Crop = None,
    skip_bad_images: Annotated[
        bool,
        typer.Option(
            help="skip (with a warning) scenes whose image is missing or corrupt instead of "
            "failing",
        ),
    ] = False,
    clients: Annotated[int, typer.Option(help="clients of the split shown")] = 2,
) -> None:
    """Validate FOLDER (a MANNERS-DB-layout folder) and summarise it: its scenes, and
    their split between the clients."""
    # lazy: torch, PIL and numpy
    from fedlgr.shell.data.dataset import load_split
    from fedlgr.shell.data.summary import describe_scenes, describe_split

    bad = "skip" if skip_bad_images else "error"
    config = conf.DataConfig(
        path=folder,
        modality=modality,
        image_size=size,
        crop=crop,
        clients=clients,
        on_bad_image=bad,
    )
    start = time.perf_counter()
    with Progress("decoding images", unit="img") as bar:  # each image decoded at most once
        scenes, split = load_split(config, progress=bar)
    print(describe_scenes(scenes))
    print(f"\nloaded in {time.perf_counter() - start:.2f} s\n")
    print(describe_split(split))
