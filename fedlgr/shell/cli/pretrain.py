"""``fedlgr pretrain``: an offline stand-in for ImageNet weights (see fedlgr.shell.pretrain)."""

from __future__ import annotations

import argparse
from pathlib import Path

from fedlgr.shell.cli.parser import Verbs, crop
from fedlgr.shell.config import DataConfig
from fedlgr.shell.console import Progress


def add_parser(verbs: Verbs) -> None:
    parser = verbs.add_parser(
        "pretrain",
        help="pretrain a MobileNetV2 root on scene descriptors (no labels), offline",
        description="Train a MobileNetV2 root to predict each scene's 27 descriptors and 2 mode "
        "flags from its image (no appropriateness labels) and save it for model.weights=FILE: an "
        "offline stand-in for ImageNet weights. Use a dataset other than the one you evaluate on, "
        "e.g. fedlgr data synth --out data/pretrain-synth --seed 1000 --scenes 2000.",
    )
    parser.add_argument("--data", type=Path, required=True, help="a MANNERS-DB-layout folder")
    parser.add_argument(
        "--out", type=Path, required=True, help="the root's state-dict file to write"
    )
    parser.add_argument("--width", type=float, default=1.0, help="MobileNetV2 width multiplier")
    parser.add_argument("--images", type=int, default=16000, help="augmented images to train on")
    parser.add_argument("--size", type=int, default=128, help="image width and height in pixels")
    parser.add_argument(
        "--crop", type=crop, default=None, help="LEFT,TOP,RIGHT,BOTTOM before resizing"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the augmentation and the root")
    parser.set_defaults(run=pretrain)


def pretrain(args: argparse.Namespace) -> int:
    # lazy: torch, torchvision and PIL
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.pretrain import pretrain_root

    data = DataConfig(path=args.data, image_size=args.size, crop=args.crop)
    with Progress("decoding images", unit="img") as bar:  # only when not cached yet
        scenes = load_scenes(data, progress=bar)
    with Progress("pretraining", unit="img") as bar:
        result = pretrain_root(
            scenes, args.out, width=args.width, images=args.images, seed=args.seed, progress=bar
        )
    print(
        f"wrote {result.path}: {result.images} images in {result.seconds:.0f} s, descriptor MSE "
        f"{result.first_loss:.3f} -> {result.last_loss:.3f} (standardised). Use it with "
        f"model.weights={result.path} model.width={args.width:g}"
    )
    return 0
