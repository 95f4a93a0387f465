"""A Flower round's wall time, today's protocol against the one before issue 21.

Real federations on localhost, each a SuperLink with TLS and SuperNode authentication
and two SuperNodes started with ``fedlgr deploy`` as docs/deployment.md says
(``tests/support/flower.py``): one runs this checkout, one this checkout with
``--cold-apps`` (Flower's own SuperExec; ``--no-cold`` leaves it out), one the commit ``--before``
(default fa15ccd, the last before issue 21: a train and an evaluate exchange per round,
one Flower ``Array`` per tensor, no gateway), from a git worktree put first on
``PYTHONPATH``. Each runs FedRootAvg for 3 rounds on the tiny debug config with its robot
services warm (a 1-round run first), alternating, ``--repeats`` times. Each run's output
is read line by line and stamped: the table shows the time to the ServerApp's first line,
the exchanges and what follows the last one. Last, the time ``fedlgr deploy run`` takes to
report a config typo. ``--quick``: a smoke run of this checkout alone (no ``--before``, no
``--cold-apps``, no warm-up run), one round, once; the ratio to the commit before is not
measured then.

    uv run python bench/flower.py [--repeats 2] [--rounds 3] [--before fa15ccd] [--quick]

Run it on a quiet machine: the exchanges wait on processes that Flower starts, and any
other work on the cores stretches them.
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fedlgr.shell.data.synth import synthesize  # noqa: E402
from tests.support.flower import Federation  # noqa: E402

CONFIG = ROOT / "conf" / "debug" / "tiny.yaml"
EXCHANGE = re.compile(r"round (\d+), [^:]*(train|evaluate): (\d+) of (\d+) replies \(([\d.]+) s\)")


def timed_run(fed, overrides: list[str]) -> dict:
    """One ``fedlgr deploy run``: its wall time, phases and exit status."""
    started = time.monotonic()
    proc = fed.run(CONFIG, overrides)
    first = last_exchange = None
    exchanges: list[float] = []
    lines = []
    for line in proc.stdout:
        now = time.monotonic() - started
        lines.append(line)
        if first is None and " rounds x " in line:
            first = now
        found = EXCHANGE.search(line)
        if found:
            exchanges.append(float(found.group(5)))
            last_exchange = now
    proc.wait()
    wall = time.monotonic() - started
    if proc.returncode != 0:
        sys.exit("".join(lines[-40:]) + f"\nbench: the run failed (exit {proc.returncode})")
    return {"wall": wall, "first": first, "exchanges": exchanges, "after": wall - last_exchange}


def old_federation(folder: Path, before: str):
    """A federation running commit ``before`` (a worktree first on PYTHONPATH)."""
    tree = folder / "before"
    subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), before],
        check=True,
        capture_output=True,
    )
    spec = importlib.util.spec_from_file_location(
        "before_federation", tree / "tests" / "flower_federation.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    fed = module.Federation(folder / "federation-before")
    fed.env["PYTHONPATH"] = str(tree)
    return fed, tree


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--before", default="fa15ccd", help="the commit to compare with")
    parser.add_argument(
        "--cold",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also run this checkout with --cold-apps (Flower's own SuperExec: a process per "
        "ClientApp message and per ServerApp run), to show what the warm executor saves",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a smoke run: this checkout only (no --before, no --cold-apps, no warm-up run), "
        "1 round, 1 repeat; the ratio to --before is not measured",
    )
    args = parser.parse_args()
    if args.quick:
        args.rounds, args.repeats, args.cold = 1, 1, False
    folder = Path(tempfile.mkdtemp(prefix="fedlgr-bench-flower-"))
    data = folder / "data"
    synthesize(data, scenes=48, seed=7, size=32)
    store = f"sqlite:///{folder}/mlflow.db"
    now = Federation(folder / "federation")
    feds, tree = {"now": now}, None
    extra = {"now": [f"deploy.roster={now.roster}"]}
    if not args.quick:
        before, tree = old_federation(folder, args.before)
        feds = {f"before ({args.before})": before, **feds}
        extra[f"before ({args.before})"] = []
    base = [f"data.path={data}", f"tracking.uri={store}", "method=FedRootAvg"]
    flags = {name: [] for name in feds}  # of fedlgr deploy superlink / supernode
    if args.cold:
        cold = Federation(folder / "federation-cold")
        feds["now, --cold-apps"] = cold
        extra["now, --cold-apps"] = [f"deploy.roster={cold.roster}"]
        flags["now, --cold-apps"] = ["--cold-apps"]
    results: dict[str, list[dict]] = {name: [] for name in feds}
    try:
        for name, fed in feds.items():
            cold = flags[name]  # the before-commit's Federation takes no flags
            fed.start_superlink(*([cold] if cold else []))
            for client, robot in enumerate(("robot0", "robot1")):
                fed.start_supernode(
                    robot, fed.node_key(robot), client, data, *([cold] if cold else [])
                )
            if args.quick:
                continue
            print(f"{name}: warming the robot services (a 1-round run) ...", flush=True)
            warm = [*base, *extra[name], "federated.rounds=1", f"tracking.run_name=warm-{name}"]
            print(f"  {timed_run(fed, warm)['wall']:.1f} s", flush=True)
        for repeat in range(args.repeats):
            order = list(feds) if repeat % 2 == 0 else list(reversed(feds))  # no order bias
            for name in order:
                overrides = [*base, *extra[name], f"federated.rounds={args.rounds}"]
                run = timed_run(feds[name], [*overrides, f"tracking.run_name={name}-{repeat}"])
                results[name].append(run)
                print(
                    f"  {name} #{repeat}: {run['wall']:.1f} s ({len(run['exchanges'])} exchanges)",
                    flush=True,
                )
        started = time.monotonic()
        typo = now.run(CONFIG, [*base, *extra["now"], "federated.roundz=3"])
        out, _ = typo.communicate(timeout=300)
        typo_s = time.monotonic() - started
    finally:
        for fed in feds.values():
            fed.stop()
        if tree is not None:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)])
    print()
    warmth = "services cold (--quick)" if args.quick else "services warm"
    print(f"FedRootAvg, {args.rounds} rounds, 2 robots on localhost, {warmth}")
    print(f"medians of {args.repeats} runs each, seconds")
    print("| code | wall | to ServerApp's first line | exchanges (each) | after the last |")
    print("|---|---|---|---|---|")
    for name, runs in results.items():
        each = [x for r in runs for x in r["exchanges"]]
        print(
            f"| {name} | {statistics.median(r['wall'] for r in runs):.1f} "
            f"| {statistics.median(r['first'] for r in runs):.1f} "
            f"| {len(runs[0]['exchanges'])} x {statistics.median(each):.1f} "
            f"| {statistics.median(r['after'] for r in runs):.1f} |"
        )
    new = statistics.median(r["wall"] for r in results["now"])
    if args.quick:
        ok_wall = True
        print("\nnow / before: not measured (--quick)")
    else:
        old = statistics.median(r["wall"] for r in results[f"before ({args.before})"])
        ok_wall = new <= old / 3
        print(f"\nnow / before: {new / old:.2f} (target <= 0.33: {'met' if ok_wall else 'MISSED'})")
    last = out.strip().splitlines()[-1] if out.strip() else ""
    print(f"config typo reported in {typo_s:.1f} s (exit {typo.returncode}): {last}")
    ok = typo.returncode == 1 and "roundz" in last and typo_s < 5
    print(f"typo target (< 5 s, one line naming it): {'met' if ok else 'MISSED'}")
    return 0 if ok and ok_wall else 1


if __name__ == "__main__":
    raise SystemExit(main())
