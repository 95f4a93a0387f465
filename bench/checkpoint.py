"""Checkpoint cost per round. Run: ``uv run python bench/checkpoint.py``.

Side by side in one process: one round of the demo config (conf/experiment/demo.yaml:
2 clients, half-width MobileNetV2, 128 px, augmented) and the checkpoint written after it
(``fedlgr.shell.run.life.RunLife.checkpoint``: the runtime's state gathered, written to a
temporary file in the folder, renamed), best of ``--repeats``; then the checkpoint of the
full-width MobileNetV2 with 2 and 10 clients (after one short round, so that every Adam
state exists): seconds and MB.
Target: the demo's checkpoint costs under 5% of its round.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

from figures import report  # bench/figures.py, beside this script

TARGETS = {"demo_checkpoint_share_%": (5.0, "max")}


def setup(tmp: str, overrides: list[str]):
    from fedlgr.core.in_process import Orchestrator
    from fedlgr.shell.config import CONF_DIR, load_config
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.data.splits import make_split
    from fedlgr.shell.run.experiment import make_fabric

    config = load_config(
        CONF_DIR / "experiment" / "demo.yaml",
        [
            f"data.path={tmp}/synth",
            f"data.cache_dir={tmp}/cache",
            "tracking.enabled=false",
            "runtime.progress=false",
            *overrides,
        ],
    )
    scenes = load_scenes(config.data)
    fabric = make_fabric(config)
    return fabric, Orchestrator(fabric, config, scenes, make_split(scenes.table, config.data))


def timed_checkpoint(fabric, orchestrator, log, folder: Path) -> tuple[float, float]:
    """Seconds to write the checkpoint, and its size in MB."""
    from fedlgr.shell.run import checkpoint as ckpt
    from fedlgr.shell.run.life import checkpoint_state
    from fedlgr.shell.run.result import ExperimentResult

    start = time.perf_counter()
    result = ExperimentResult(orchestrator.config, [log], run_id="bench")
    whole = checkpoint_state(orchestrator.config, result, orchestrator.state_dict(), 0.0)
    path = ckpt.save(fabric, folder, log.round, whole, keep=1)
    seconds = time.perf_counter() - start
    return seconds, path.stat().st_size / 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=1000, help="synthetic scenes (demo: 1000)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    import torch

    from fedlgr.core.messages import RoundPlan
    from fedlgr.shell.data.synth import synthesize
    from fedlgr.shell.machine import torch_threads

    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        synthesize(Path(tmp) / "synth", args.scenes, seed=0, size=128)
        fabric, orchestrator = setup(tmp, [])
        torch.set_num_threads(torch_threads(orchestrator.config, 1))
        rounds, saves, size = [], [], 0.0
        for repeat in range(args.repeats):
            log = orchestrator.run_round(RoundPlan(repeat + 1))
            rounds.append(log.seconds)
            seconds, size = timed_checkpoint(fabric, orchestrator, log, Path(tmp) / "demo")
            saves.append(seconds)
        figures["demo_round_s"] = min(rounds)
        figures["demo_checkpoint_s"] = min(saves)
        figures["demo_checkpoint_mb"] = size
        figures["demo_checkpoint_share_%"] = 100 * min(saves) / min(rounds)
        for clients in (2, 10):
            fabric, orchestrator = setup(
                tmp, ["model.width=1.0", f"data.clients={clients}", "train.max_batches=1"]
            )
            log = orchestrator.run_round(RoundPlan(1))
            best = min(
                timed_checkpoint(fabric, orchestrator, log, Path(tmp) / f"full{clients}")
                for _ in range(args.repeats)
            )
            figures[f"full_{clients}c_checkpoint_s"] = best[0]
            figures[f"full_{clients}c_checkpoint_mb"] = best[1]

    print(
        f"fedlgr checkpoint benchmark - {date.today()} - {platform.machine()}, "
        f"{os.cpu_count()} cores, torch {torch.__version__}, {torch.get_num_threads()} threads"
    )
    print(
        f"demo config ({args.scenes} synthetic scenes at 128 px, 2 clients, MobileNetV2 x0.5, "
        f"augmented x2, 1 epoch): round and checkpoint after it, best of {args.repeats}; "
        "full-width MobileNetV2, FedAvg: checkpoint after one round"
    )
    failed = report(figures, TARGETS)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
