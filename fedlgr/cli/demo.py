"""``fedlgr demo``: the README's main job on the embedded synthetic data.

Generates the synthetic living room if the folder has no ``all_data.csv``, then runs a
short FedAvg vs FedRootAvg comparison on it (``conf/experiment/demo.yaml``: 2 clients,
random-init MobileNetV2, augmentation) tracked in MLflow, and prints a table of test
scores and per-client costs.
"""

from __future__ import annotations

import argparse

from fedlgr.config import CONF_DIR
from fedlgr.console import Progress, table

DEMO_CONFIG = CONF_DIR / "experiment" / "demo.yaml"
METHODS = ("FedAvg", "FedRootAvg")


def demo(args: argparse.Namespace) -> int:
    from fedlgr.config import load_config
    from fedlgr.data.synth import synthesize
    from fedlgr.federated.experiment import run_experiment

    if not (args.data / "all_data.csv").is_file():
        print(f"no dataset in {args.data}: synthesising {args.scenes} scenes (seed {args.seed})")
        with Progress("synthesising", unit="scene") as bar:
            synthesize(args.data, args.scenes, args.seed, force=True, progress=bar)
    overrides = [f"data.path={args.data}", f"seed={args.seed}", *args.overrides]
    if args.tracking_uri:
        overrides.append(f"tracking.uri={args.tracking_uri}")
    results = []
    for method in METHODS:
        config = load_config(DEMO_CONFIG, [*overrides, f"method={method}"])
        print()
        results.append(run_experiment(config))
    rows = []
    for r in results:
        last = r.final
        rows.append(
            [
                r.config.method_name,
                last.mean("test_loss"),
                last.mean("test_rmse"),
                last.mean("test_pcc"),
                last.mean("cpu_s"),
                f"{last.mean('bytes_up') / 2**20:.2f} MB",
                f"{r.seconds:.0f}",
            ]
        )
    print(
        f"\nFedAvg vs FedRootAvg on {args.data} after {results[0].config.federated.rounds} rounds "
        "(test scores: mean over clients; costs: per client per round)"
    )
    print(table(["method", "loss", "RMSE", "PCC", "CPU s", "upload", "run s"], rows))
    print("\nCompare the runs: uv run mlflow ui --backend-store-uri sqlite:///mlflow.db")
    return 0
