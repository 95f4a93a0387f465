"""``fedlgr demo``: the README's main job on the embedded synthetic data.

For now (before training lands) it generates the synthetic living room if the folder has
no ``all_data.csv``, loads it through the same reader real MANNERS-DB data takes, and
prints the dataset and its federated split.
"""

from __future__ import annotations

import argparse

from fedlgr.console import Progress


def demo(args: argparse.Namespace) -> int:
    from fedlgr.cli.data import summarise
    from fedlgr.data.config import DataConfig
    from fedlgr.data.synth import synthesize

    if not (args.data / "all_data.csv").is_file():
        print(f"no dataset in {args.data}: synthesising {args.scenes} scenes (seed {args.seed})")
        with Progress("synthesising", unit="scene") as bar:
            synthesize(args.data, args.scenes, args.seed, force=True, progress=bar)
    summarise(DataConfig(path=args.data, clients=args.clients, seed=args.seed))
    return 0
