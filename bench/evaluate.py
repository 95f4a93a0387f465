"""Evaluation benchmark (issue 12, point 3). Run: ``uv run python bench/evaluate.py``.

FedRootAvg with 10 clients on the synthetic data (128 px, random-init MobileNetV2): the
seconds one round's evaluation takes when every client runs its whole model over the test
set (what fedlgr did) and when the clients, which hold the same root after the download,
share one root pass and add their own tops (``ClientSide.predictions``). Both in this
process, alternating, median of ``--repeats``; the outputs are checked to be identical.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

from figures import report  # bench/figures.py, beside this script

TARGETS = {"eval_ratio": (0.25, "max")}


def evaluation_cost(side, received, repeats: int) -> dict[str, float]:
    """Seconds of one round's evaluation of ``side``'s clients (a ``ClientSide`` whose
    clients hold ``received``) with whole models (before point 3) and as fedlgr does it
    now; median of ``repeats``, alternating; the outputs are checked to be identical."""
    import torch

    from fedlgr.core.evaluation import predict

    batch = side.config.train.eval_batch_size
    scored = [c.index for c in side.clients]

    def whole_models():
        return [predict(c.model, side.test_inputs, batch) for c in side.clients]

    def shared_root():
        preds = side.predictions(received, scored)
        return [preds[index] for index in scored]

    def timed(fn):
        start = time.perf_counter()
        out = fn()
        return time.perf_counter() - start, out

    before, after = [], []
    for repeat in range(repeats):  # alternating order: neither always runs warm
        if repeat % 2:
            shared_s, shared = timed(shared_root)
            whole_s, whole = timed(whole_models)
        else:
            whole_s, whole = timed(whole_models)
            shared_s, shared = timed(shared_root)
        assert all(torch.equal(a, b) for a, b in zip(whole, shared, strict=True))
        before.append(whole_s)
        after.append(shared_s)
    return {
        "eval_s_before": statistics.median(before),
        "eval_s_after": statistics.median(after),
        "eval_ratio": statistics.median(a / b for a, b in zip(after, before, strict=True)),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=400)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--clients", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    import torch

    from fedlgr.core.in_process import Orchestrator
    from fedlgr.shell.config import load_config
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.data.splits import make_split
    from fedlgr.shell.data.synth import synthesize
    from fedlgr.shell.machine import torch_threads
    from fedlgr.shell.run.experiment import make_fabric

    with tempfile.TemporaryDirectory() as tmp:
        synthesize(Path(tmp) / "synth", args.scenes, seed=0, size=args.size)
        config = load_config(
            None,
            [
                f"data.path={tmp}/synth",
                f"data.cache_dir={tmp}/cache",
                f"data.image_size={args.size}",
                f"data.clients={args.clients}",
                "method=FedRootAvg",
                "model.weights=none",
                "tracking.enabled=false",
            ],
        )
        scenes = load_scenes(config.data)
    split = make_split(scenes.table, config.data)
    torch.set_num_threads(torch_threads(config, 1))
    orchestrator = Orchestrator(make_fabric(config), config, scenes, split)
    side, received = orchestrator.client_side, orchestrator.server.global_weights
    batch = config.train.eval_batch_size
    figures = evaluation_cost(side, received, args.repeats)
    print(
        f"fedlgr evaluation benchmark - {date.today()} - {platform.machine()}, "
        f"{os.cpu_count()} cores, torch {torch.__version__}, {torch.get_num_threads()} threads"
    )
    print(
        f"FedRootAvg, {args.clients} clients, {len(side.test_inputs)} test scenes at "
        f"{args.size} px, batch {batch}, random-init MobileNetV2; median of {args.repeats}; "
        "outputs identical"
    )
    failed = report(figures, TARGETS)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
