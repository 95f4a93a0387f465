"""``fedlgr data synth | show | check``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from fedlgr.core.data.columns import LABEL_SHORT_NAMES
from fedlgr.shell.cli.parser import Verbs, crop
from fedlgr.shell.config import DataConfig
from fedlgr.shell.console import Progress, table
from fedlgr.shell.signals import terminate_as_interrupt


def add_parser(verbs: Verbs) -> None:
    data = verbs.add_parser("data", help="create, inspect and check datasets")
    data_verbs = data.add_subparsers(dest="data_verb", metavar="VERB", required=True)
    _add_synth(data_verbs)
    _add_show(data_verbs)
    _add_check(data_verbs)


def _add_synth(data_verbs: Verbs) -> None:
    parser = data_verbs.add_parser(
        "synth", help="write a synthetic living room in the MANNERS-DB layout"
    )
    parser.add_argument("--out", type=Path, required=True, help="folder to write")
    parser.add_argument("--scenes", type=int, default=1000, help="scenes to write")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scenes and ratings")
    parser.add_argument("--size", type=int, default=128, help="image width and height in pixels")
    parser.add_argument("--force", action="store_true", help="overwrite a non-empty folder")
    parser.set_defaults(run=synth)


def _add_show(data_verbs: Verbs) -> None:
    parser = data_verbs.add_parser("show", help="contact sheet of a few scenes with their labels")
    parser.add_argument("folder", type=Path, help="a MANNERS-DB-layout folder")
    parser.add_argument(
        "--out", type=Path, default=Path("contact_sheet.png"), help="the PNG file to write"
    )
    parser.add_argument("--scenes", type=int, default=8, help="scenes on the sheet")
    parser.add_argument("--seed", type=int, default=0, help="seed of the choice of scenes")
    parser.add_argument(
        "--crop", type=crop, default=None, help="LEFT,TOP,RIGHT,BOTTOM before resizing"
    )
    parser.set_defaults(run=show)


def _add_check(data_verbs: Verbs) -> None:
    parser = data_verbs.add_parser("check", help="validate a dataset folder and summarise it")
    parser.add_argument("folder", type=Path, help="a MANNERS-DB-layout folder")
    parser.add_argument(
        "--modality",
        choices=["image", "features"],
        default="image",
        help="check the images too, or the CSV's descriptors alone",
    )
    parser.add_argument(
        "--size", type=int, default=128, help="image width and height to decode to, in pixels"
    )
    parser.add_argument(
        "--crop", type=crop, default=None, help="LEFT,TOP,RIGHT,BOTTOM before resizing"
    )
    parser.add_argument(
        "--skip-bad-images",
        action="store_true",
        help="skip (with a warning) scenes whose image is missing or corrupt instead of failing",
    )
    parser.add_argument("--clients", type=int, default=2, help="clients of the split shown")
    parser.set_defaults(run=check)


def synth(args: argparse.Namespace) -> int:
    from fedlgr.shell.data.synth import synthesize  # lazy: PIL and numpy

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
    from fedlgr.shell.data.contact_sheet import contact_sheet  # lazy: torch and PIL

    out = contact_sheet(args.folder, args.out, args.scenes, args.seed, args.crop)
    print(f"wrote {out}")
    return 0


def summarise(config) -> None:
    """Load the dataset of ``config`` (decoding images at most once), print it and its split."""
    # lazy: torch, PIL and numpy
    from fedlgr.shell.data.dataset import load_split
    from fedlgr.shell.data.summary import describe_scenes, describe_split

    start = time.perf_counter()
    with Progress("decoding images", unit="img") as bar:
        scenes, split = load_split(config, progress=bar)
    print(describe_scenes(scenes))
    print(f"\nloaded in {time.perf_counter() - start:.2f} s\n")
    print(describe_split(split))


def check(args: argparse.Namespace) -> int:
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
