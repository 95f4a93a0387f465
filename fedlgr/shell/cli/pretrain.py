"""``fedlgr pretrain``: an offline stand-in for ImageNet weights (see fedlgr.shell.pretrain)."""

from __future__ import annotations

import argparse

from fedlgr.shell.console import Progress


def pretrain(args: argparse.Namespace) -> int:
    from fedlgr.shell.data.config import DataConfig
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
