"""The paper's CPU figure, reproduced side by side with the real per-client cost (issue 23).
Run: ``uv run python bench/paper_cpu.py``  (~1 minute on 2 cores; nothing else running).

FedAvg and FedRootAvg, 2 clients, 240 scenes of the synthetic living room's images at
128 px (the paper's size; a half-width random MobileNetV2, the demo's settings, no
augmentation), ``--rounds`` rounds each, one after
the other in this one process, with ``federated.server_eval=auto``: the server scores the
global model every round (and before round 1) where it holds one - FedAvg - as the
authors' code gave every full-model baseline an ``evaluate_fn`` and no FedRoot variant.
Each run is measured both ways:

* **the paper's way**: the CPU of the process that ran the server (its aggregation and
  its evaluation; the authors' driver process, whose clients trained in Ray workers it
  did not count) divided by clients x rounds - ``mean/cost/paper_cpu_s``;
* **fedlgr's way**: each client's own CPU for its local training and evaluation, per
  round, averaged over clients and rounds - ``mean/cost/cpu_s``.

It prints both figures for each method and FedRootAvg's "reduction" against FedAvg each
way: a large one the paper's way, about none per client.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
from datetime import date
from pathlib import Path

METHODS = ("FedAvg", "FedRootAvg")


def measure(data: Path, rounds: int, threads: int, size: int) -> dict[str, dict[str, float]]:
    from fedlgr.shell.config import CONF_DIR, load_config
    from fedlgr.shell.run.experiment import run_experiment

    out = {}
    for method in METHODS:
        config = load_config(
            CONF_DIR / "experiment" / "demo.yaml",
            [
                f"method={method}",
                f"data.path={data}",
                f"data.image_size={size}",
                "data.augment=false",
                f"federated.rounds={rounds}",
                "federated.server_eval=auto",
                f"runtime.threads={threads}",
                "runtime.progress=false",
                "tracking.enabled=false",
            ],
        )
        result = run_experiment(config, echo=lambda *a, **k: None)
        out[method] = result.cost_means() | {"server_evaluates": config.federated.server_evaluates}
    return out


def reduction(full: float, root: float) -> str:
    return f"{100 * (full - root) / full:.0f}%"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--size", type=int, default=128, help="image size (the paper's: 128)")
    parser.add_argument("--scenes", type=int, default=240)
    args = parser.parse_args(argv)
    from fedlgr.shell.data.synth import synthesize

    with tempfile.TemporaryDirectory(prefix="fedlgr-bench-") as tmp:
        data = Path(tmp) / "synth"
        synthesize(data, scenes=args.scenes, seed=0, size=args.size)
        found = measure(data, args.rounds, args.threads, args.size)
    print(
        f"bench/paper_cpu.py, {date.today()}, {platform.processor() or platform.machine()}, "
        f"2 clients, {args.rounds} rounds, {args.scenes} synthetic scenes at {args.size} px, "
        f"{args.threads} torch thread(s)"
    )
    print(f"{'method':<11} {'server eval':>11} {'paper-style CPU s':>18} {'per-client CPU s':>17}")
    for method in METHODS:
        f = found[method]
        print(
            f"{method:<11} {'yes' if f['server_evaluates'] else 'no':>11} "
            f"{f['mean/cost/paper_cpu_s']:>18.3f} {f['mean/cost/cpu_s']:>17.3f}"
        )
    full, root = found["FedAvg"], found["FedRootAvg"]
    paper = reduction(full["mean/cost/paper_cpu_s"], root["mean/cost/paper_cpu_s"])
    own = reduction(full["mean/cost/cpu_s"], root["mean/cost/cpu_s"])
    print(f"FedRootAvg's reduction against FedAvg: paper-style {paper}, per client {own}")
    print("(per client per round; the paper's Table III: FedAvg 19.06 s, FedRootAvg 2.55 s, -87%)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
