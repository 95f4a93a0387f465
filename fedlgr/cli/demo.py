"""``fedlgr demo``: the README's main job on the embedded synthetic data.

For now (before training lands) it generates the synthetic living room if the folder has
no ``all_data.csv``, loads it through the same reader real MANNERS-DB data takes, and
prints the dataset and its federated split.
"""

from __future__ import annotations

import argparse
import time

from fedlgr.console import Progress


def demo(args: argparse.Namespace) -> int:
    from fedlgr.data.config import DataConfig
    from fedlgr.data.dataset import load_scenes
    from fedlgr.data.splits import make_split
    from fedlgr.data.summary import describe_scenes, describe_split
    from fedlgr.data.synth import synthesize

    if not (args.data / "all_data.csv").is_file():
        print(f"no dataset in {args.data}: synthesising {args.scenes} scenes (seed {args.seed})")
        with Progress("synthesising", unit="scene") as bar:
            synthesize(args.data, args.scenes, args.seed, force=True, progress=bar)
    config = DataConfig(path=args.data, clients=args.clients, seed=args.seed)
    start = time.perf_counter()
    with Progress("decoding images", unit="img") as bar:
        scenes = load_scenes(config, progress=bar)
    print(describe_scenes(scenes))
    print(f"\nloaded in {time.perf_counter() - start:.2f} s\n")
    print(describe_split(make_split(scenes.table, config)))
    return 0
