"""The cost of secure aggregation (``deploy.secagg``, Flower's SecAgg+) on robots: the same
small Flower federation run plain and with SecAgg+, side by side.

A real federation on localhost (``tests/support/flower.py``: a SuperLink with TLS and
SuperNode authentication, ``--robots`` SuperNodes, ``fedlgr deploy`` as
docs/deployment.md says), FedAvg on the tiny debug config, the robot services warm (a
1-round run first). Three settings, alternating, ``--repeats`` times: plain with one
exchange per round (the default ``deploy.evaluate=with_next_round``), plain with a
training and an evaluation exchange (``separate``, which is how a SecAgg+ round runs),
and SecAgg+. Read back from MLflow: seconds per round (``round/seconds``), bytes per
robot and round (``cost/bytes_up`` - for SecAgg+ the masked vector -, ``cost/bytes_down``)
and SecAgg+'s key stages (``secagg/*_bytes_*``: whole messages, protobuf-encoded).

``--quick``: a smoke run, SecAgg+ alone (bench/flower.py's smoke run covers plain runs): 2
robots, one round, no warm-up run.

    uv run python bench/secagg.py [--robots 3] [--rounds 2] [--repeats 1] [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

import mlflow

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fedlgr.shell.data.synth import synthesize  # noqa: E402
from tests.support.flower import Federation  # noqa: E402

CONFIG = ROOT / "conf" / "debug" / "tiny.yaml"
SETTINGS = {
    "plain (one exchange per round)": [],
    "plain, deploy.evaluate=separate": ["deploy.evaluate=separate"],
    "SecAgg+": ["deploy.secagg.enabled=true"],
}
STAGES = ("setup", "keys", "unmask")


def run(fed: Federation, overrides: list[str], name: str, store: str) -> str:
    proc = fed.run(CONFIG, [*overrides, f"tracking.run_name={name}"])
    out, _ = proc.communicate(timeout=1800)
    if proc.returncode != 0:
        sys.exit(out[-4000:] + f"\nbench: {name} failed (exit {proc.returncode})")
    client = mlflow.MlflowClient(store)
    experiment = client.get_experiment_by_name("fedlgr-debug")
    [found] = client.search_runs([experiment.experiment_id], f"attributes.run_name = '{name}'")
    return found.info.run_id


def figures(store: str, run_id: str, robots: int) -> dict[str, float]:
    """Per round (median over rounds), per robot (mean over robots)."""
    client = mlflow.MlflowClient(store)

    def each(key: str) -> list[float]:
        return [m.value for m in client.get_metric_history(run_id, key)]

    out = {"round s": statistics.median(each("round/seconds"))}
    for way in ("up", "down"):
        values = [v for c in range(robots) for v in each(f"cost/client{c}/bytes_{way}")]
        out[f"bytes {way}"] = statistics.mean(values)
        stages = [sum(each(f"secagg/{s}_bytes_{way}")) / robots for s in STAGES]
        rounds = len(each("round/seconds"))
        out[f"key stages {way}"] = sum(stages) / rounds
    secure = each("secagg/seconds")
    out["SecAgg+ exchanges s"] = statistics.median(secure) if secure else 0.0
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a smoke run: SecAgg+ alone, 2 robots, 1 round, 1 repeat, no warm-up run",
    )
    args = parser.parse_args()
    settings = SETTINGS
    if args.quick:
        args.robots, args.rounds, args.repeats = 2, 1, 1
        settings = {"SecAgg+": SETTINGS["SecAgg+"]}
    folder = Path(tempfile.mkdtemp(prefix="fedlgr-bench-secagg-"))
    data = folder / "data"
    synthesize(data, scenes=16 * args.robots, seed=7, size=32)
    store = f"sqlite:///{folder}/mlflow.db"
    fed = Federation(folder / "federation")
    base = [f"data.path={data}", f"tracking.uri={store}", "method=FedAvg"]
    base += [f"data.clients={args.robots}", "tracking.detail_metrics=true"]
    results: dict[str, list[dict]] = {name: [] for name in settings}
    try:
        fed.start_superlink()
        base.append(f"deploy.roster={fed.roster}")
        for client in range(args.robots):
            name = f"robot{client}"
            fed.start_supernode(name, fed.node_key(name), client, data)
        if not args.quick:
            print("warming the robot services (a 1-round run) ...", flush=True)
            run(fed, [*base, "federated.rounds=1"], "warm", store)
        for repeat in range(args.repeats):
            order = list(settings) if repeat % 2 == 0 else list(reversed(settings))
            for name in order:
                overrides = [*base, *settings[name], f"federated.rounds={args.rounds}"]
                run_id = run(fed, overrides, f"{name}-{repeat}", store)
                results[name].append(figures(store, run_id, args.robots))
                print(f"  {name} #{repeat}: {results[name][-1]}", flush=True)
    finally:
        fed.stop()
    print(f"\nFedAvg, tiny config, {args.robots} robots on localhost, {args.rounds} rounds,")
    warmth = "services cold (--quick)" if args.quick else "services warm"
    print(f"{warmth}; medians of {args.repeats} run(s); per round, bytes per robot")
    keys = list(next(iter(results.values()))[0])
    print("| setting | " + " | ".join(keys) + " |")
    print("|---|" + "---|" * len(keys))
    for name, runs in results.items():
        cells = [statistics.median(r[k] for r in runs) for k in keys]
        shown = [
            f"{c:.1f}" if k.endswith(" s") else f"{c / 1024:.1f} KB"
            for k, c in zip(keys, cells, strict=True)
        ]
        print(f"| {name} | " + " | ".join(shown) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
