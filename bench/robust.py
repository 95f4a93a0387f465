"""Robustness benchmark (issue 37). Run: ``uv run python bench/robust.py`` (~10 min on 2
cores for the descriptors; add ``--modality image`` for the images, much longer).

On the synthetic living room (1000 scenes), ``--clients`` clients (10), ``--rounds``
rounds of ``--epochs`` local epochs, for each ``--modality`` (``features``: the MLP root
over the descriptors; ``image``: a random-init MobileNetV2 of ``--width`` at ``--size``
px): FedAvg, FedMedian, FedTrimmedAvg and Krum, with the whole model and with FedRoot's
root only, against 0, 1, 2 and 3 Byzantine clients flipping the sign of their update
(``federated.faults.attack=sign_flip``); and FedAvg / FedRootAvg with 0, 0.2 and 0.5 of
the clients dropping out of each round. The robust methods are set for up to 3 faulty
clients of 10: FedTrimmedAvg ``beta=0.3``, Krum ``f=3`` (``m=1``). Every cell is the mean
over ``--seeds`` (0 and 1): the final test RMSE and PCC (mean over clients) and the
server's CPU seconds per round (aggregation; no server evaluation). Prints the tables,
checks the acceptance target (2 of 10 sign-flipping: the best robust method's RMSE within
5% of clean FedAvg's, FedAvg's own worse than that) and writes ``robust.png`` and
``robust.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

STRATEGIES = ["Avg", "Median", "TrimmedAvg", "Krum"]
ROBUST = ["federated.trimmed.beta=0.3", "federated.krum.f=3", "federated.krum.m=1"]
TARGET = 0.05  # the best robust RMSE within 5% of clean FedAvg's (2 of 10 sign-flipping)


def method(strategy: str, scope: str) -> str:
    """FedAvg, FedMedian, FedTrimmedAvg, Krum; FedRootAvg, FedRootMedian, ..."""
    if scope == "root":
        return f"FedRoot{strategy}"
    return "Krum" if strategy == "Krum" else f"Fed{strategy}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--modality", nargs="+", default=["features"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--clients", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--epochs", type=int, default=1)
    parser.add_argument("--byzantine", nargs="+", type=int, default=[0, 1, 2, 3])
    parser.add_argument("--dropout", nargs="+", type=float, default=[0.0, 0.2, 0.5])
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--width", type=float, default=0.25)
    parser.add_argument("--set", nargs="*", default=[], metavar="key=value", dest="overrides")
    parser.add_argument("--workdir", type=Path, default=None, help="keep data and runs here")
    parser.add_argument("--out", type=Path, default=Path("."), help="robust.png, robust.json")
    args = parser.parse_args()

    import torch

    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        cells = {m: run_modality(m, work, args) for m in args.modality}
    print(
        f"\nfedlgr robustness benchmark - {date.today()} - {platform.machine()}, "
        f"{os.cpu_count()} cores, torch {torch.__version__}; "
        f"{time.perf_counter() - start:.0f} s in all; {args.clients} clients, "
        f"{args.rounds} rounds x {args.epochs} epochs, seeds {args.seeds}"
    )
    missed = 0
    for modality, table in cells.items():
        missed += show(modality, table, args)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "robust.json").write_text(
        json.dumps(
            {m: {" | ".join(map(str, k)): v for k, v in t.items()} for m, t in cells.items()}
        )
    )
    plot(cells, args, args.out / "robust.png")
    return 1 if missed else 0


def run_modality(modality: str, work: Path, args) -> dict[tuple, dict[str, float]]:
    """{(scope, strategy, "byzantine" | "dropout", level): mean figures over the seeds}."""
    from fedlgr.shell.config import CONF_DIR, load_config
    from fedlgr.shell.data.synth import synthesize
    from fedlgr.shell.run.experiment import run_experiment

    size = args.size if modality == "image" else 64
    data = work / f"synth-{size}"
    if not (data / "all_data.csv").is_file():
        synthesize(data, 1000, seed=0, size=size, force=True)
    uri = f"sqlite:///{work / 'mlflow.db'}"
    stamp = time.strftime("%Y%m%d-%H%M%S")
    common = [
        f"data.path={data}",
        f"data.cache_dir={work / 'cache'}",
        f"data.clients={args.clients}",
        f"federated.rounds={args.rounds}",
        f"train.epochs={args.epochs}",
        f"tracking.uri={uri}",
        f"tracking.experiment=bench-robust-{modality}-{stamp}",
        "tracking.system_metrics=false",
        "runtime.progress=false",
        *ROBUST,
    ]
    if modality == "image":
        common += [f"data.image_size={size}", f"model.width={args.width}"]
    else:
        common += ["data.modality=features", "model.root=mlp"]
    plan = [
        (scope, strategy, "byzantine", k)
        for k in args.byzantine
        for scope in ("full", "root")
        for strategy in STRATEGIES
    ] + [(scope, "Avg", "dropout", p) for p in args.dropout if p for scope in ("full", "root")]
    print(f"{modality}: MLflow experiment bench-robust-{modality}-{stamp} in {uri}", flush=True)
    cells = {}
    for scope, strategy, kind, level in plan:
        faults = (
            [f"federated.faults.byzantine={level}", "federated.faults.attack=sign_flip"]
            if kind == "byzantine"
            else [f"federated.faults.dropout={level}"]
        )
        figures = []
        for seed in args.seeds:
            name = method(strategy, scope)
            config = load_config(
                CONF_DIR / "experiment" / "demo.yaml",
                [
                    *common,
                    f"method={name}",
                    f"seed={seed}",
                    *faults,
                    *args.overrides,
                    f"tracking.run_name={name}-{kind}{level}-seed{seed}",
                ],
            )
            t = time.perf_counter()
            result = run_experiment(config, echo=lambda *a, **k: None)
            last = result.rounds[-1]
            server = [r.server.get("cost/server_cpu_s", 0.0) for r in result.rounds]
            figures.append(
                {
                    "rmse": last.mean("test/rmse"),
                    "pcc": last.mean("test/pcc"),
                    "server_cpu_s": statistics.mean(server),
                    "refused": sum(len(r.refused) for r in result.rounds),
                }
            )
            print(
                f"  {name} {kind}={level} seed {seed}: {time.perf_counter() - t:.0f} s", flush=True
            )
        cells[scope, strategy, kind, level] = {
            key: statistics.mean(f[key] for f in figures) for key in figures[0]
        }
    return cells


def show(modality: str, cells: dict, args) -> int:
    """The tables of one modality and its target check; 1 if the target is missed."""
    print(f"\n== {modality}: final test RMSE / PCC / server CPU s per round (mean of seeds)")
    for scope in ("full", "root"):
        print(f"\n{'method':<18}" + "".join(f"  {k} sign-flipping      " for k in args.byzantine))
        for strategy in STRATEGIES:
            row = [
                cells[scope, strategy, "byzantine", k]
                for k in args.byzantine
                if (scope, strategy, "byzantine", k) in cells
            ]
            text = "".join(f"  {c['rmse']:.3f} {c['pcc']:.3f} {c['server_cpu_s']:.4f}" for c in row)
            print(f"{method(strategy, scope):<18}{text}")
    print(f"\n{'drop-out':<18}" + "".join(f"  {p:<22}" for p in args.dropout))
    for scope in ("full", "root"):
        row = [
            cells.get((scope, "Avg", "dropout", p)) or cells[scope, "Avg", "byzantine", 0]
            for p in args.dropout
        ]
        print(
            f"{method('Avg', scope):<18}"
            + "".join(f"  {c['rmse']:.3f} {c['pcc']:.3f}        " for c in row)
        )
    missed = 0
    if 2 in args.byzantine and 0 in args.byzantine:
        for scope in ("full", "root"):
            clean = cells[scope, "Avg", "byzantine", 0]["rmse"]
            attacked = cells[scope, "Avg", "byzantine", 2]["rmse"]
            best = min(cells[scope, s, "byzantine", 2]["rmse"] for s in STRATEGIES[1:])
            ok = best <= (1 + TARGET) * clean and attacked > (1 + TARGET) * clean
            missed += not ok
            print(
                f"{modality} {method('Avg', scope)}: clean {clean:.3f}; 2 sign-flipping: "
                f"{method('Avg', scope)} {attacked:.3f}, best robust {best:.3f} "
                f"(target <= {1 + TARGET:.2f} x clean, {method('Avg', scope)} above it): "
                f"{'ok' if ok else 'MISSED'}"
            )
    return 1 if missed else 0


def plot(cells: dict, args, path: Path) -> None:
    """Final RMSE against the number of sign-flipping clients, per method and scope."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(cells)
    fig, axes = plt.subplots(len(rows), 2, figsize=(10, 3.6 * len(rows)), squeeze=False)
    for i, modality in enumerate(rows):
        for j, scope in enumerate(("full", "root")):
            ax = axes[i][j]
            for strategy in STRATEGIES:
                levels = [
                    k
                    for k in args.byzantine
                    if (scope, strategy, "byzantine", k) in cells[modality]
                ]
                ax.plot(
                    levels,
                    [cells[modality][scope, strategy, "byzantine", k]["rmse"] for k in levels],
                    marker="o",
                    label=method(strategy, scope),
                )
            ax.set_title(
                f"{modality}, {'whole model' if scope == 'full' else 'FedRoot (root only)'}"
            )
            ax.set_xlabel(f"sign-flipping clients of {args.clients}")
            ax.set_ylabel("final test RMSE")
            ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    sys.exit(main())
