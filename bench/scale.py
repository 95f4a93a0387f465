"""Scale benchmark (issue 40): a thousand clients on one machine. Run: ``uv run python
bench/scale.py`` (``--quick``: every case at a tiny scale, ~5 min on 2 cores; ``--cases
'avg-*' lgr-200``: a subset; ``--reference PATH``: also the code before issue 40, a checkout
with its own ``.venv``; bench/README.md says how long the full run takes).

Each case is one ``run_experiment`` in a fresh process (``bench/scale_case.py``, run with the
measured checkout's python), so that its peak memory is its own; a case over
``--memory-gb`` of resident memory or ``--timeout`` seconds is killed and shown as such, a
case the code refuses as "refused: <why>". Every case trains on the same synthetic living
room (10,000 scenes at 128 px, ``--quick`` 300, written once into ``--work`` with their
decoded-image cache), tests on the same quarter of it, and trains one local epoch of one
batch of 16 per chosen client a round (``train.max_batches=1``), with MLflow in a sqlite
store of its own and a checkpoint every round: ``conf/experiment/demo.yaml``'s width-0.5
MobileNetV2 and 2 augmented copies, 3 rounds (``--rounds``); FedLGR
``conf/experiment/demo_fcl.yaml``'s two tasks, circle then arrow, one round each.

* the grid: FedAvg and FedRootAvg on the images, FedLGR on the images and on the
  descriptors (``data.modality=features``), for 10, 100 and 1000 clients (fraction 1 up to
  100, 0.01 for 1000);
* **A**: at 1000 clients (fraction 0.01: 10 clients of ~7.5 scenes, 15 augmented samples:
  one batch each) FedAvg and FedRootAvg stay within 4 GB (peak RSS), and a round takes at
  most 1.5x the round of 10 clients at fraction 1 (10 batches of 16 a round too);
* **B**: FedLGR with 200 clients at fraction 0.05 runs its two tasks within 4 GB.

The settings issue 40 adds (``runtime.idle_clients=--idle``, ``federated.evaluate=--evaluate``)
are passed where the code knows them; the table names those a checkout left out. Prints a
markdown table (round 1, the median of the later rounds, CPU seconds a round, peak RSS, each
round's MLflow logging and checkpoint, and the store, checkpoint folder and results.csv on
disk), checks A and B on this checkout's code (exit status 1 if missed), writes every
figure to ``--work``/results.json and plots wall time and peak RSS against clients to
``--out``/scale.png.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from datetime import date
from pathlib import Path

import matplotlib
import psutil
from figures import report  # bench/figures.py, beside this script
from scale_case import PREFIX

from fedlgr.core.settings import default_cache_dir
from fedlgr.shell.data.synth import synthesize

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.ticker import NullFormatter

ROOT = Path(__file__).resolve().parents[1]
CHILD = Path(__file__).resolve().parent / "scale_case.py"
FULL = {
    "scenes": 10_000,
    "rounds": 3,
    "rounds_per_task": 1,
    "grid": ((10, 1.0), (100, 1.0), (1000, 0.01)),
    "B": (200, 0.05),
    "lgr": (),  # FedLGR at its defaults
}
QUICK = {  # 225 training scenes: 14 a client at 16 clients, both tasks in each
    "scenes": 300,
    "rounds": 2,
    "rounds_per_task": 1,
    "grid": ((4, 1.0), (16, 0.25)),
    "B": (8, 0.5),
    "lgr": ("continual.lgr.epochs=20",),  # a smoke run: the VAEs' fits are most of its time
}
SIZE = 128  # px, as conf/data/synth.yaml
FAMILIES = {  # name -> (method, modality)
    "avg": ("FedAvg", "image"),
    "root": ("FedRootAvg", "image"),
    "lgr-features": ("FedLGR", "features"),
    "lgr": ("FedLGR", "image"),
}
LIMIT_MIB = 4096  # A and B: peak RSS
RATIO = 1.5  # A: a round at the most clients / at the fewest
NEW, BEFORE = "issue 40", "before"


@dataclass(frozen=True)
class Case:
    name: str
    family: str
    clients: int
    fraction: float
    role: str = "grid"  # grid | B

    @property
    def method(self) -> str:
        return FAMILIES[self.family][0]

    @property
    def modality(self) -> str:
        return FAMILIES[self.family][1]


@dataclass(frozen=True)
class Side:
    """A checkout whose code is measured: its root and its python."""

    label: str
    root: Path
    python: str


@dataclass(frozen=True)
class Options:
    """What every case of a run shares."""

    rounds: int
    rounds_per_task: int
    threads: int | None = None
    idle: str = "auto"
    evaluate: str = "chosen"
    eval_clients: int = 10
    timeout: float = 1800.0
    memory_mib: float = 8192.0
    settings: tuple[str, ...] = ()  # key=value for every run
    lgr: tuple[str, ...] = ()  # key=value for the FedLGR runs


def main(argv: list[str] | None = None) -> int:
    args = arguments(argv)
    sizes = QUICK if args.quick else FULL
    options = Options(
        rounds=args.rounds or sizes["rounds"],
        rounds_per_task=sizes["rounds_per_task"],
        threads=args.threads,
        idle=args.idle,
        evaluate=args.evaluate,
        eval_clients=args.eval_clients,
        timeout=args.timeout,
        memory_mib=args.memory_gb * 1024,
        settings=tuple(args.set),
        lgr=sizes["lgr"],
    )
    chosen = select(cases(sizes), args.cases)
    sides = [Side(NEW, ROOT, sys.executable)]
    if args.reference is not None:
        ref = args.reference.resolve()
        python = ref / ".venv" / "bin" / "python"
        if not python.is_file():
            raise SystemExit(f"--reference {ref}: no {python} (uv sync there first)")
        sides.append(Side(BEFORE, ref, str(python)))
    work = args.work.resolve()
    start = time.perf_counter()
    data = synth(work, sizes["scenes"])
    for side in sides if any(c.modality == "image" for c in chosen) else []:
        warm(side, data, work, options)
    results = []
    for case in chosen:  # the sides one after the other, case by case
        for side in sides:
            row = measure(side, case, data, work, options)
            print(f"  {side.label:>8} {case.name:<16} {row['status']}", flush=True)
            results.append(row)
    (work / "results.json").write_text(json.dumps(results, indent=1))
    print(header(sides, sizes, options, time.perf_counter() - start))
    print(table(results))
    figures, targets = checks(results, sizes)
    print("\nTargets (issue 40; the code of this checkout)\n")
    missed = report(figures, targets)
    if not figures:
        print("  (none: neither A's nor B's cases ran)")
    args.out.mkdir(parents=True, exist_ok=True)
    plot(results, sizes, args.out / "scale.png")
    print(f"\nfigures: {work / 'results.json'}\nplot: {args.out / 'scale.png'}")
    return 1 if missed else 0


def arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="every case at a tiny scale")
    parser.add_argument("--cases", nargs="+", default=["*"], help="names or patterns")
    parser.add_argument("--reference", type=Path, help="a checkout before issue 40 (.venv)")
    parser.add_argument("--work", type=Path, default=default_cache_dir() / "bench-scale")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "img")
    parser.add_argument("--rounds", type=int, help="federated.rounds of FedAvg and FedRootAvg")
    parser.add_argument("--threads", type=int, help="runtime.threads (default: the machine's)")
    parser.add_argument("--idle", default="auto", help="runtime.idle_clients, where known")
    parser.add_argument("--evaluate", default="chosen", help="federated.evaluate, where known")
    parser.add_argument("--eval-clients", type=int, default=10, help="federated.eval_clients")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per case")
    parser.add_argument("--memory-gb", type=float, default=8.0, help="resident memory per case")
    parser.add_argument("--set", nargs="+", default=[], help="key=value for every run")
    return parser.parse_args(argv)


def cases(sizes: dict) -> list[Case]:
    """The grid, by clients then family, then B."""
    grid = [
        Case(f"{family}-{n}", family, n, fraction)
        for n, fraction in sizes["grid"]
        for family in FAMILIES
    ]
    n, fraction = sizes["B"]
    return [*grid, Case(f"lgr-{n}", "lgr", n, fraction, role="B")]


def select(all_cases: list[Case], patterns: list[str]) -> list[Case]:
    chosen = [c for c in all_cases if any(fnmatch.fnmatchcase(c.name, p) for p in patterns)]
    if not chosen:
        names = ", ".join(c.name for c in all_cases)
        raise SystemExit(f"--cases {' '.join(patterns)}: no such case (cases: {names})")
    return chosen


def synth(work: Path, scenes: int) -> Path:
    """``scenes`` synthetic scenes at 128 px, written once (seed 7, as the README's)."""
    data = work / f"synth-{scenes}-{SIZE}"
    if not (data / "all_data.csv").is_file():
        print(f"  writing {scenes} synthetic scenes into {data}", flush=True)
        synthesize(data, scenes, seed=7, size=SIZE, force=True)
    return data


# ---------------------------------------------------------------------- one case


def spec(case: Case, side: Side, data: Path, run_dir: Path, options: Options) -> dict:
    """What ``scale_case.py`` runs for ``case`` with ``side``'s code."""
    fcl = case.method == "FedLGR"
    preset = side.root / "conf" / "experiment" / ("demo_fcl.yaml" if fcl else "demo.yaml")
    overrides = [
        f"method={case.method}",
        f"data.path={data}",
        f"data.cache_dir={data.parent / 'cache'}",
        f"data.clients={case.clients}",
        f"federated.fraction={case.fraction}",
        "train.epochs=1",
        "train.max_batches=1",
        "seed=0",
        "runtime.progress=false",
        f"tracking.uri=sqlite:///{run_dir / 'mlflow.db'}",
        f"tracking.checkpoint_dir={run_dir / 'checkpoints'}",
        "tracking.experiment=scale",
        "tracking.checkpoint=1",
    ]
    if fcl:  # demo_fcl.yaml's two tasks, fewer rounds
        overrides.append(f"continual.rounds_per_task={options.rounds_per_task}")
        overrides += options.lgr
    else:
        overrides.append(f"federated.rounds={options.rounds}")
    if case.modality == "features":
        overrides += ["data.modality=features", "model.root=mlp"]
    if options.threads is not None:
        overrides.append(f"runtime.threads={options.threads}")
    overrides += options.settings
    optional = [f"runtime.idle_clients={options.idle}", f"federated.evaluate={options.evaluate}"]
    if options.evaluate == "sample":
        optional.append(f"federated.eval_clients={options.eval_clients}")
    return {
        "config": str(preset),
        "overrides": overrides,
        "optional": optional,
        "checkpoints": str(run_dir / "checkpoints"),
    }


def measure(side: Side, case: Case, data: Path, work: Path, options: Options) -> dict:
    """Run ``case`` with ``side``'s code in a fresh folder: its figures and its store's size."""
    run_dir = work / "runs" / side.label.replace(" ", "-") / case.name
    shutil.rmtree(run_dir, ignore_errors=True)
    run_dir.mkdir(parents=True)
    figures = run_case(side.python, spec(case, side, data, run_dir, options), run_dir, options)
    figures |= on_disk(run_dir)
    return {
        "side": side.label,
        **asdict(case),
        "method": case.method,
        "modality": case.modality,
        **figures,
    }


def warm(side: Side, data: Path, work: Path, options: Options) -> None:
    """Decode the images into the cache once, before any case is timed."""
    run_dir = work / "runs" / "warm"
    run_dir.mkdir(parents=True, exist_ok=True)
    case = Case("warm", "avg", 2, 1.0)
    job = spec(case, side, data, run_dir, options) | {"warm": True}
    done = run_case(side.python, job, run_dir, options)
    print(f"  {side.label:>8} image cache: {done['status']}", flush=True)


def run_case(python: str, job: dict, run_dir: Path, options: Options) -> dict:
    """Run ``scale_case.py`` with ``python`` on ``job`` in ``run_dir``; its line's figures,
    or a status saying why there are none (killed: over the memory or the time allowed)."""
    env = {k: v for k, v in os.environ.items() if k != "VIRTUAL_ENV"}
    out, err = run_dir / "case.out", run_dir / "case.err"
    with out.open("w") as stdout, err.open("w") as stderr:
        process = subprocess.Popen(
            [python, str(CHILD), json.dumps(job)],
            cwd=run_dir,  # MLflow's artifacts land beside the store
            stdout=stdout,
            stderr=stderr,
            env=env,
        )
        killed, polled = watch(process, options.timeout, options.memory_mib)
    lines = [x for x in out.read_text().splitlines() if x.startswith(PREFIX)]
    if killed:
        figures = {"status": killed}
    elif lines:
        figures = json.loads(lines[-1].removeprefix(PREFIX))
    else:
        last = [x for x in err.read_text().splitlines() if x.strip()][-1:] or ["no output"]
        figures = {"status": f"failed (exit {process.returncode}): {last[0][:200]}"}
    return {**figures, "polled_rss_mib": polled}


def watch(process: subprocess.Popen, timeout: float, memory_mib: float) -> tuple[str, float]:
    """Wait for ``process``, killing it past ``timeout`` seconds or ``memory_mib`` of resident
    memory (its children's too); why it was killed ("" if it was not), and the most
    resident memory seen (MiB, sampled every 0.2 s)."""
    start, peak = time.perf_counter(), 0.0
    watched = psutil.Process(process.pid)
    while process.poll() is None:
        try:
            rss = sum(p.memory_info().rss for p in [watched, *watched.children(recursive=True)])
        except psutil.Error:  # it has just exited
            rss = 0
        peak = max(peak, rss / 2**20)
        why = ""
        if peak > memory_mib:
            why = f"over {memory_mib / 1024:g} GB"
        elif time.perf_counter() - start > timeout:
            why = f"over {timeout:g} s"
        if why:
            process.kill()
            process.wait()
            return why, peak
        time.sleep(0.2)
    return "", peak


def on_disk(run_dir: Path) -> dict:
    """The MLflow store (its database and artifacts) and results.csv, after the run."""
    store = sum(
        p.stat().st_size
        for p in run_dir.rglob("*")
        if p.is_file() and p.name not in ("case.out", "case.err") and "checkpoints" not in p.parts
    )
    results = sum(p.stat().st_size for p in run_dir.rglob("results.csv"))
    return {"store_mib": store / 2**20, "results_kib": results / 1024}


# ---------------------------------------------------------------------- figures


def summary(row: dict) -> dict:
    """A case's figures for the table: round 1, the median of the later rounds, and per
    round (medians) its CPU seconds, MLflow logging and checkpoint; None where unmeasured."""
    wall, cpu = row.get("wall_s") or [], row.get("cpu_s") or []
    later = wall[1:] or wall
    return {
        "round1_s": wall[0] if wall else None,
        "round_s": statistics.median(later) if later else None,
        "cpu_s": statistics.median(cpu[1:] or cpu) if cpu else None,
        "rss_mib": row.get("peak_rss_mib"),
        "tracking_s": _median(row.get("tracking_s")),
        "checkpoint_s": _median(row.get("checkpoint_s")),
    }


def _median(values: list[float] | None) -> float | None:
    return statistics.median(values) if values else None


COLUMNS = [  # header, key, format
    ("round 1 (s)", "round1_s", ".2f"),
    ("round (s, median of later)", "round_s", ".2f"),
    ("CPU (s/round)", "cpu_s", ".2f"),
    ("peak RSS (MiB)", "rss_mib", ".0f"),
    ("MLflow (s/round)", "tracking_s", ".3f"),
    ("checkpoint (s/round)", "checkpoint_s", ".3f"),
    ("checkpoint folder (MiB)", "checkpoint_mib", ".1f"),
    ("store (MiB)", "store_mib", ".1f"),
    ("results.csv (KiB)", "results_kib", ".1f"),
]


def table(results: list[dict]) -> str:
    """One markdown row per case and code."""
    head = ["case", "method", "data", "clients", "fraction", "code", *(c[0] for c in COLUMNS)]
    lines = ["| " + " | ".join([*head, "note"]) + " |", "|---" * (len(head) + 1) + "|"]
    for row in results:
        figures = {**row, **summary(row)}
        ok = row["status"] == "ok"
        cells = [row["name"], row["method"], row["modality"], str(row["clients"])]
        cells += [f"{row['fraction']:g}", row["side"]]
        cells += [
            "—" if not ok or figures.get(key) is None else format(figures[key], fmt)
            for _, key, fmt in COLUMNS
        ]
        note = row["status"] if not ok else ""
        if row.get("dropped"):  # settings this code does not know
            note = "without " + ", ".join(o.split("=")[0] for o in row["dropped"])
        lines.append("| " + " | ".join([*cells, note]) + " |")
    return "\n".join(lines)


def checks(results: list[dict], sizes: dict) -> tuple[dict, dict]:
    """A and B's figures (this checkout's code) and their targets; a case that did not
    finish counts as infinite."""
    new = {r["name"]: r for r in results if r["side"] == NEW}
    figures: dict[str, float] = {}
    targets: dict[str, tuple[float, str]] = {}
    (few, _), (most, _) = sizes["grid"][0], sizes["grid"][-1]
    for family in ("avg", "root"):
        small, big = new.get(f"{family}-{few}"), new.get(f"{family}-{most}")
        if big is not None:
            figures[f"{big['name']} RSS MiB"] = _rss(big)
            targets[f"{big['name']} RSS MiB"] = (LIMIT_MIB, "max")
        if small is not None and big is not None:
            ratio = f"{big['name']}/{small['name']} round"
            figures[f"{small['name']} round s"] = _round(small)
            figures[f"{big['name']} round s"] = _round(big)
            figures[ratio] = _round(big) / _round(small)
            targets[ratio] = (RATIO, "max")
    b = next((r for r in new.values() if r["role"] == "B"), None)
    if b is not None:
        figures[f"{b['name']} RSS MiB"] = _rss(b)
        targets[f"{b['name']} RSS MiB"] = (LIMIT_MIB, "max")
    return figures, targets


def _rss(row: dict) -> float:
    return row["peak_rss_mib"] if row["status"] == "ok" else float("inf")


def _round(row: dict) -> float:
    value = summary(row)["round_s"] if row["status"] == "ok" else None
    return float("inf") if value is None else value


def header(sides: list[Side], sizes: dict, options: Options, seconds: float) -> str:
    code = "; ".join(f"{s.label}: {s.root} ({_commit(s.root)})" for s in sides)
    threads = options.threads or "the machine's default"
    return (
        f"\nfedlgr scale benchmark - {date.today()} - {platform.machine()}, "
        f"{os.cpu_count()} cores, {psutil.virtual_memory().total / 2**30:.0f} GiB; "
        f"{sizes['scenes']} scenes at {SIZE} px; threads {threads}; "
        f"runtime.idle_clients={options.idle}, federated.evaluate={options.evaluate} "
        f"where known; {code}; {seconds:.0f} s in all\n"
    )


def _commit(root: Path) -> str:
    done = subprocess.run(
        ["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    )
    return done.stdout.strip() or "not a git checkout"


def plot(results: list[dict], sizes: dict, path: Path) -> None:
    """Per-round wall time and peak RSS against clients (log x): a line per family and code
    (this checkout's solid, the reference's dashed); B as a star; 4 GB dotted."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.4))
    for ax, key, label in zip(
        axes, ("round_s", "rss_mib"), ("wall time a round (s)", "peak RSS (MiB)"), strict=True
    ):
        for i, family in enumerate(FAMILIES):
            for side, style in ((NEW, "-"), (BEFORE, "--")):
                rows = [
                    r
                    for r in results
                    if r["family"] == family and r["side"] == side and r["status"] == "ok"
                ]
                grid = sorted((r["clients"], summary(r)[key]) for r in rows if r["role"] == "grid")
                name = f"{FAMILIES[family][0]} {FAMILIES[family][1]}, {side}"
                if grid:
                    x, y = zip(*grid, strict=True)
                    ax.plot(x, y, style, marker="o", color=f"C{i}", label=name)
                for r in (r for r in rows if r["role"] == "B"):
                    b = f"B: {name}, fraction {r['fraction']:g}"
                    ax.plot(r["clients"], summary(r)[key], "*", ms=12, color=f"C{i}", label=b)
        if key == "rss_mib":
            ax.axhline(LIMIT_MIB, ls=":", color="grey", label="4 GB (A, B)")
            ax.legend(handles=ax.get_lines()[-1:], fontsize=8, loc="center right")
        else:
            ax.set_yscale("log")
        clients = sorted({r["clients"] for r in results})
        ax.set_xscale("log")
        ax.set_xticks(clients, [str(n) for n in clients])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("clients")
        ax.set_ylabel(label)
    fig.suptitle(f"A thousand clients: {sizes['scenes']} synthetic scenes, one batch a client")
    # the lines' legend below both panels, where it hides no point
    fig.legend(handles=axes[0].get_lines(), fontsize=8, ncol=3, loc="lower center")
    fig.tight_layout(rect=(0, 0.17, 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
