"""Data-path benchmark (issue: data layer). Run: ``uv run python bench/data.py``.

Prints: seconds to synthesise 1000 scenes at 128 px; seconds to load them cold (decode
every PNG) and warm (from the decode-once cache); augmented images per second through the
training-time pipeline at batch 16 (gather from the uint8 store, flip/rotate, normalise);
and the wall time of ``fedlgr --help``. Each figure is checked against its target.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

from figures import report  # bench/figures.py, beside this script

TARGETS = {  # figure -> (target, "max" | "min")
    "synthesis_s": (60.0, "max"),
    "warm_load_s": (2.0, "max"),
    "augmented_img_per_s": (2000.0, "min"),
    "help_s": (2.0, "max"),
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=1000)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--epochs", type=int, default=2, help="augmented epochs to time")
    args = parser.parse_args()

    from fedlgr.shell.machine import tune_allocator

    tuned = tune_allocator()  # as the fedlgr command does

    import numpy as np
    import torch

    from fedlgr.core.data.augment import Augment, SceneBatches
    from fedlgr.shell.config import DataConfig
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.data.synth import synthesize

    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        data, cache = Path(tmp) / "synth", Path(tmp) / "cache"
        summary = synthesize(data, args.scenes, seed=0, size=args.size)
        figures["synthesis_s"] = summary.seconds

        config = DataConfig(path=data, image_size=args.size, cache_dir=cache)
        start = time.perf_counter()
        load_scenes(config)
        figures["cold_load_s"] = time.perf_counter() - start
        start = time.perf_counter()
        scenes = load_scenes(config)
        figures["warm_load_s"] = time.perf_counter() - start

    batches = SceneBatches(
        scenes.images,
        scenes.targets,
        np.arange(len(scenes)),
        16,
        copies=10,
        augment=Augment(),
        seed=0,
    )
    next(iter(batches))  # warm-up
    start, n = time.perf_counter(), 0
    for _ in range(args.epochs):
        for x, _y in batches:
            n += len(x)
    figures["augmented_img_per_s"] = n / (time.perf_counter() - start)

    script = Path(sys.executable).with_name("fedlgr")  # the console script uv installed
    command = [str(script)] if script.exists() else [sys.executable, "-m", "fedlgr"]
    start = time.perf_counter()
    done = subprocess.run([*command, "--help"], capture_output=True, text=True)
    figures["help_s"] = time.perf_counter() - start
    if done.returncode != 0:  # say why rather than a bare CalledProcessError
        sys.exit(f"bench: fedlgr --help failed (exit {done.returncode}):\n{done.stderr[-2000:]}")

    print(
        f"fedlgr data benchmark - {date.today()} - {platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"allocator tuning {'on' if tuned else 'off'}"
    )
    print(
        f"{args.scenes} scenes at {args.size} px; augmented pipeline: batch 16, 10 copies per "
        f"scene, {args.epochs} epochs = {n} images"
    )
    failed = report(figures, TARGETS)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
