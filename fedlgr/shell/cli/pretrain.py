"""``fedlgr pretrain``: an offline stand-in for ImageNet weights (see fedlgr.shell.pretrain)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from fedlgr.shell import config as conf  # its names load when used: pydantic
from fedlgr.shell.cli.verb import Crop, Verbs
from fedlgr.shell.console import Progress

app = Verbs()


@app.command(
    "pretrain", short_help="pretrain a MobileNetV2 root on scene descriptors (no labels), offline"
)
def pretrain(
    data: Annotated[Path, typer.Option(help="a MANNERS-DB-layout folder")],
    out: Annotated[Path, typer.Option(help="the root's state-dict file to write")],
    width: Annotated[float, typer.Option(help="MobileNetV2 width multiplier")] = 1.0,
    images: Annotated[int, typer.Option(help="augmented images to train on")] = 16000,
    size: Annotated[int, typer.Option(help="image width and height in pixels")] = 128,
    crop: Crop = None,
    seed: Annotated[int, typer.Option(help="seed of the augmentation and the root")] = 0,
) -> None:
    """Train a MobileNetV2 root to predict each scene's 27 descriptors and 2 mode flags
    from its image (no appropriateness labels) and save it for model.weights=FILE: an
    offline stand-in for ImageNet weights. Use a dataset other than the one you evaluate
    on, e.g. fedlgr data synth --out data/pretrain-synth --seed 1000 --scenes 2000."""
    # lazy: torch, torchvision and PIL
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.pretrain import pretrain_root

    with Progress("decoding images", unit="img") as bar:  # only when not cached yet
        scenes = load_scenes(conf.DataConfig(path=data, image_size=size, crop=crop), progress=bar)
    with Progress("pretraining", unit="img") as bar:
        result = pretrain_root(scenes, out, width=width, images=images, seed=seed, progress=bar)
    print(
        f"wrote {result.path}: {result.images} images in {result.seconds:.0f} s, descriptor MSE "
        f"{result.first_loss:.3f} -> {result.last_loss:.3f} (standardised). Use it with "
        f"model.weights={result.path} model.width={width:g}"
    )
