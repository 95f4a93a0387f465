"""``fedlgr data synth | show | check``."""

from __future__ import annotations

import argparse
import time

from fedlgr.shell.console import Progress, table


def synth(args: argparse.Namespace) -> int:
    from fedlgr.core.data.columns import LABEL_SHORT_NAMES
    from fedlgr.shell.data.synth import synthesize
    from fedlgr.shell.signals import terminate_as_interrupt

    # SIGTERM (timeout, Slurm) is a Ctrl-C: synthesize removes what it had written
    with terminate_as_interrupt(), Progress("synthesising", unit="scene") as bar:
        s = synthesize(args.out, args.scenes, args.seed, args.size, force=args.force, progress=bar)
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
    return 0


def show(args: argparse.Namespace) -> int:
    from fedlgr.shell.data.contact_sheet import contact_sheet

    out = contact_sheet(args.folder, args.out, args.scenes, args.seed, args.crop)
    print(f"wrote {out}")
    return 0


def summarise(config) -> None:
    """Load the dataset of ``config`` (decoding images at most once), print it and its split."""
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.data.splits import make_split
    from fedlgr.shell.data.summary import describe_scenes, describe_split

    start = time.perf_counter()
    with Progress("decoding images", unit="img") as bar:
        scenes = load_scenes(config, progress=bar)
    print(describe_scenes(scenes))
    print(f"\nloaded in {time.perf_counter() - start:.2f} s\n")
    print(describe_split(make_split(scenes.table, config)))


def check(args: argparse.Namespace) -> int:
    from fedlgr.shell.data.config import DataConfig

    summarise(
        DataConfig(
            path=args.folder,
            modality=args.modality,
            image_size=args.size,
            crop=args.crop,
            clients=args.clients,
            on_bad_image="skip" if args.skip_bad_images else "error",
        )
    )
    return 0
