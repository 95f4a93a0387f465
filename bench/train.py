"""Training benchmark (issue: FL benchmark). Run: ``uv run python bench/train.py``.

On the synthetic data (synthesised into a temp folder), 2 clients, one round, 128 px,
batch 16, random-init MobileNetV2, FedAvg: prints images per second of client training,
CPU seconds per client per round, seconds per round (training + aggregation + evaluation
of all clients), and the ratio of the orchestrator's training time to a plain PyTorch loop
that trains the same model on the same batches for the same number of steps in one
process. Both run in this process, interleaved, best of ``--repeats``.
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

TARGETS = {"ratio": (1.10, "max"), "client_img_per_s": (140.0, "min")}


def plain_loop(model, optimizer, batches, steps: int, channels_last: bool) -> float:
    """The reference: forward, MSE, backward, step - nothing else. Returns seconds."""
    import torch

    model.train()
    warm_x, warm_y = batches[0]  # one untimed step, as the orchestrator warms up too
    torch.nn.functional.mse_loss(
        model(warm_x.contiguous(memory_format=torch.channels_last)), warm_y
    ).backward()
    optimizer.zero_grad(set_to_none=True)
    start = time.perf_counter()
    for x, y in batches[:steps]:
        if channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        loss = torch.nn.functional.mse_loss(model(x), y)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    return time.perf_counter() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scenes", type=int, default=400, help="synthetic scenes (2 clients get 3/4)"
    )
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()

    from fedlgr.runtime import tune_allocator

    tuned = tune_allocator()
    import torch

    from fedlgr.config import load_config
    from fedlgr.data.dataset import load_scenes
    from fedlgr.data.splits import make_split
    from fedlgr.data.synth import synthesize
    from fedlgr.federated.experiment import make_fabric
    from fedlgr.federated.orchestrator import Orchestrator, torch_threads
    from fedlgr.models.scholar import build_scholar

    with tempfile.TemporaryDirectory() as tmp:
        synthesize(Path(tmp) / "synth", args.scenes, seed=0, size=args.size)
        config = load_config(
            None,
            [
                f"data.path={tmp}/synth",
                f"data.cache_dir={tmp}/cache",
                f"data.image_size={args.size}",
                "data.clients=2",
                "train.epochs=1",
                "train.batch_size=16",
                "federated.rounds=1",
                "model.weights=none",
                "tracking.enabled=false",
            ],
        )
        scenes = load_scenes(config.data)
    split = make_split(scenes.table, config.data)
    fabric = make_fabric(config)
    torch.set_num_threads(torch_threads(config, 1))

    # Each repeat times both; the order alternates so that neither always runs warm.
    # Figures are taken from the best (fastest) repeat of each, ratio included.
    train_times, plain_times, cpus, rounds = [], [], [], []
    samples = 0.0
    for repeat in range(args.repeats):
        orchestrator = Orchestrator(fabric, config, scenes, split)
        steps = sum(len(c.batches) for c in orchestrator.clients)
        # The plain loop: one model, the same batches (pre-gathered, so the loop measures
        # training alone), the same number of steps.
        batches = [b for c in orchestrator.clients for b in c.batches]
        torch.manual_seed(config.seed)
        model = build_scholar(config)
        optimizer = model.configure_optimizers()
        if repeat % 2:
            plain_times.append(
                plain_loop(model, optimizer, batches, steps, config.model.channels_last)
            )
        log = orchestrator.run_round(1)
        if not repeat % 2:
            plain_times.append(
                plain_loop(model, optimizer, batches, steps, config.model.channels_last)
            )
        wall, trained, cpu = (log.column(f).tolist() for f in ("wall_s", "train_samples", "cpu_s"))
        samples = sum(trained)
        train_times.append(sum(wall))
        cpus.append(sum(cpu) / len(cpu))
        rounds.append(log.seconds)
    best = {
        "client_img_per_s": samples / min(train_times),
        "cpu_s_per_client_round": min(cpus),
        "round_s": min(rounds),
        "plain_img_per_s": samples / min(plain_times),
        "ratio": min(train_times) / min(plain_times),
    }

    print(
        f"fedlgr training benchmark - {date.today()} - {platform.machine()}, "
        f"{os.cpu_count()} cores, "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, allocator tuning "
        f"{'on' if tuned else 'off'}"
    )
    print(
        f"synthetic data, {args.scenes} scenes at {args.size} px, 2 clients x "
        f"{len(split.clients[0].train)} scenes, one round of FedAvg, batch 16, random-init "
        f"MobileNetV2, channels_last; best of {args.repeats} (alternating order)"
    )
    failed = report(best, TARGETS)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
