"""FCL benchmark (issue: FCL). Run: ``uv run python bench/fcl.py`` (~25 minutes on 2 cores).

On the synthetic living room (1000 scenes, 128 px, 2 clients), Task 1 = circle then Task 2 =
arrow, ``--rounds-per-task`` rounds of ``--epochs`` local epochs each, every Table II method
plus FedRoot without a CL method (FedRoot-FT, on ``--seeds`` seeds). All start from one
half-width MobileNetV2 root pretrained offline on the descriptors of *other* synthetic
scenes (seed 1000; no appropriateness labels), the stand-in for the paper's ImageNet
weights. Prints per method the circle-test RMSE and PCC after Task 1 and after Task 2, the
forgetting (positive: circle got worse), and arrow after Task 2; then checks that FedRoot-FT
forgets beyond noise on every seed. Coefficients are fedlgr's defaults, not grid-searched.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

TABLE2 = [
    "FedAvg-EWC",
    "FedAvg-EWCOnline",
    "FedAvg-SI",
    "FedAvg-MAS",
    "FedAvg-NR",
    "FedRoot-EWC",
    "FedRoot-EWCOnline",
    "FedRoot-SI",
    "FedRoot-MAS",
    "FedRoot-NR",
    "FedLGR",
]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", nargs="*", default=TABLE2)
    parser.add_argument("--seeds", nargs="*", type=int, default=[0, 1], help="seeds of FedRoot-FT")
    parser.add_argument("--rounds-per-task", type=int, default=8)
    parser.add_argument("--epochs", type=int, default=2)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--width", type=float, default=0.5)
    parser.add_argument("--workdir", type=Path, default=None, help="keep data and the root here")
    args = parser.parse_args()

    from fedlgr.runtime import tune_allocator

    tune_allocator()
    import torch

    from fedlgr.cli.demo import forgetting_table
    from fedlgr.config import CONF_DIR, load_config
    from fedlgr.data.synth import synthesize
    from fedlgr.federated.experiment import run_experiment
    from fedlgr.models.pretrain import synthetic_root

    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        data = work / "synth"
        if not (data / "all_data.csv").is_file():
            synthesize(data, 1000, seed=0, size=args.size, force=True)
        root = synthetic_root(
            work / "pretrain", width=args.width, size=args.size, cache_dir=work / "cache"
        )
        common = [
            f"data.path={data}",
            f"data.cache_dir={work / 'cache'}",
            f"data.image_size={args.size}",
            f"model.width={args.width}",
            f"model.weights={root}",
            f"train.epochs={args.epochs}",
            f"continual.rounds_per_task={args.rounds_per_task}",
            "tracking.enabled=false",
            "runtime.progress=false",
        ]
        runs = [("FedRoot-FT", s) for s in args.seeds] + [(m, 0) for m in args.methods]
        results, saved = [], {}
        for method, seed in runs:
            config = load_config(
                CONF_DIR / "experiment" / "demo_fcl.yaml",
                [*common, f"method={method}", f"seed={seed}"],
            )
            t = time.perf_counter()
            result = run_experiment(config, echo=lambda *a, **k: None)
            print(f"  {method} (seed {seed}): {time.perf_counter() - t:.0f} s", flush=True)
            results.append(result)
            saved[f"{method} seed {seed}"] = {
                "after_tasks": result.after_tasks,
                "seconds": result.seconds,
            }
            (work / "fcl_results.json").write_text(json.dumps(saved, indent=1))  # nothing lost

    print(
        f"\nfedlgr FCL benchmark - {date.today()} - {platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__}; {time.perf_counter() - start:.0f} s in all"
    )
    print(
        f"synthetic data, 1000 scenes at {args.size} px, 2 clients, circle then arrow, "
        f"{args.rounds_per_task} rounds x {args.epochs} local epochs per task, "
        f"width-{args.width:g} MobileNetV2 pretrained on other scenes' descriptors; "
        "forgetting > 0: circle got worse\n"
    )
    print(forgetting_table(results, _label))
    return check_forgetting([r for r in results if r.config.method_name == "FedRoot-FT"])


def _label(result) -> str:
    name = result.config.method_name
    return f"{name} seed {result.config.seed}" if name == "FedRoot-FT" else name


def check_forgetting(ft) -> int:
    """FedRoot-FT must forget circle on every seed, beyond the round-to-round noise of the
    circle scores in the last rounds of Task 1."""
    print("\nFedRoot-FT forgetting of circle, per seed:")
    failed = 0
    for r in ft:
        per_task = r.config.continual.rounds_per_task
        circle = [log.mean("task_circle_rmse") for log in r.rounds[:per_task]]
        noise = float(np.max(np.abs(np.diff(circle[-3:])))) if len(circle) >= 3 else float("nan")
        forgot = r.after_tasks[1]["after_task2/forgetting/circle/rmse"]
        pcc = r.after_tasks[1]["after_task2/forgetting/circle/pcc"]
        ok = forgot > 3 * noise
        failed += not ok
        print(
            f"  seed {r.config.seed}: RMSE {forgot:+.3f} (PCC {pcc:+.3f}) vs noise {noise:.3f} "
            f"(largest change between the last 3 rounds of Task 1): "
            f"{'forgets' if ok else 'NOT beyond noise'}"
        )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
