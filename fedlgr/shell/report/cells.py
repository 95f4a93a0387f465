"""Which runs a table cell may average: replicates, runs whose settings differ only in seeds.

A cell of a table is (benchmark, method, clients, augmentation). It averages the runs whose
resolved configs - the flattened config each run logs as MLflow params
(:func:`fedlgr.shell.tracking.context.run_params`) - are equal except for the seeds
(:data:`SEEDS`). Runs of one cell with other settings (e.g. ``federated.rounds``) are
refused in one line that names the cell and the settings, with how to report them apart
(``--where KEY=VALUE``, or separate experiments). Two runs with the same settings AND seeds
(a repeat, e.g. a run made again after a resume test) are one replicate: the newest (by
start time) is kept, and the report says so once.

Runs without logged params (made by hand, or by something other than fedlgr's Tracker)
cannot be compared: each counts as a replicate of its own.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

from fedlgr.shell.report.runs import ReportError, RunRecord
from fedlgr.shell.tracking.context import used_settings

# The seeds: model initialisation, batch order and augmentation (``seed``), and the split of
# the scenes into clients and train/test (``data.seed``). Runs differing only here are
# replicates of one experiment.
SEEDS = ("seed", "data.seed")
# Settings that change no number a table shows, so they never split a cell: where and how a
# run is recorded (``tracking.*``: experiment, run name, checkpoints, heartbeats, system
# metrics), where and how it runs (``runtime.*``: processes, threads, concurrency,
# accelerator, progress bar, timeouts - the same training on other hardware), and the
# decoded-image cache (``data.cache``, ``data.cache_dir``).
IGNORED_PREFIXES = ("tracking.", "runtime.")
IGNORED = frozenset({"data.cache", "data.cache_dir"})

Cell = tuple[str, str, int, bool]  # benchmark, method, clients, augmentation


def cell_of(record: RunRecord) -> Cell:
    return (record.benchmark, record.method, record.clients, record.augmentation)


def describe(cell: Cell) -> str:
    """``FL FedAvg, 2 clients, without augmentation``."""
    benchmark, method, clients, augmented = cell
    augmentation = "with augmentation" if augmented else "without augmentation"
    return f"{benchmark} {method}, {clients} clients, {augmentation}"


def settings(record: RunRecord) -> dict[str, str] | None:
    """The run's settings that a cell must share: the params it uses (a run that logged
    every setting, as fedlgr did before, is read as if it had logged only those) but the
    seeds and the :data:`IGNORED` ones; None for a run that logged no params."""
    if not record.params:
        return None
    used = used_settings(record.params, record.tags.get("runtime") == "flower")
    return {
        k: v
        for k, v in used.items()
        if k not in SEEDS and k not in IGNORED and not k.startswith(IGNORED_PREFIXES)
    }


def seeds(record: RunRecord) -> str:
    """``seed=0 data.seed=0``."""
    return " ".join(f"{k}={record.params.get(k, '?')}" for k in SEEDS)


def newest_per_seed(records: Sequence[RunRecord]) -> tuple[list[RunRecord], str | None]:
    """One run per cell, settings and seeds: the newest by start time. Returns the runs
    kept and, where repeats were left out, one line that says so."""
    groups: dict[tuple, list[RunRecord]] = {}
    for r in records:
        found = settings(r)
        key = (r.run_id,) if found is None else (cell_of(r), seeds(r), *sorted(found.items()))
        groups.setdefault(key, []).append(r)
    kept, repeats = [], []
    for runs in groups.values():
        runs = sorted(runs, key=lambda r: r.start_time, reverse=True)
        kept.append(runs[0])
        if len(runs) > 1:
            older = ", ".join(r.run_id[:8] for r in runs[1:])
            repeats.append(
                f"{describe(cell_of(runs[0]))}, {seeds(runs[0])}: kept run {runs[0].run_id[:8]}, "
                f"left out {older}"
            )
    if not repeats:
        return kept, None
    left = sum(len(g) - 1 for g in groups.values())
    line = (
        f"{left} run{'s' * (left != 1)} repeat the settings and seeds of a newer run: one "
        f"seed is one replicate, the newest run kept ({'; '.join(repeats)})"
    )
    return kept, line


def best_per_cell(records: Sequence[RunRecord], objective: str) -> list[RunRecord]:
    """A sweep over coefficients has several settings per cell: the table shows the best of
    them by the sweep's objective (e.g. ``minimize test/rmse``, the paper's grid-searched
    coefficients), averaged over its seeds when the sweep has several. The runs of the best
    setting of each cell; every run where ``objective`` is not one."""
    direction, _, metric = objective.partition(" ")
    if direction not in ("minimize", "maximize") or not metric:
        return list(records)
    variants: dict[Cell, dict[tuple, list[RunRecord]]] = {}
    for r in records:
        found = settings(r)
        key = (r.run_id,) if found is None else _key(found)
        variants.setdefault(cell_of(r), {}).setdefault(key, []).append(r)
    sign = 1.0 if direction == "minimize" else -1.0

    def score(runs: list[RunRecord]) -> float:
        values = [v for v in (r.value(metric) for r in runs) if v is not None]
        return sign * sum(values) / len(values) if values else float("inf")

    return [r for cell in variants.values() for r in min(cell.values(), key=score)]


def check_cells(records: Sequence[RunRecord], source: str) -> None:
    """Refuse, in one line, a cell whose runs differ in more than their seeds."""
    cells: dict[Cell, list[dict[str, str]]] = {}
    for r in records:
        found = settings(r)
        if found is not None:
            cells.setdefault(cell_of(r), []).append(found)
    mixed = {cell: runs for cell, runs in cells.items() if len({_key(s) for s in runs}) > 1}
    if not mixed:
        return
    cell, runs = next(iter(mixed.items()))
    keys = sorted({k for s in runs for k in s if len({s.get(k) for s in runs}) > 1})
    listed = "; ".join(f"{k} ({_values(runs, k)})" for k in keys)
    example = ", ".join(f"--where {k}={runs[0].get(k, '')}" for k in keys[:1])
    more = f" (and {len(mixed) - 1} more cells)" if len(mixed) > 1 else ""
    raise ReportError(
        f"{source}: the cell {describe(cell)}{more} holds runs of other settings than their "
        f"seeds: {listed}. A cell averages only runs that differ in their seeds "
        f"({', '.join(SEEDS)}): report them apart, e.g. {example}, or run them into "
        "separate experiments (tracking.experiment=NAME)"
    )


def _key(found: dict[str, str]) -> tuple:
    return tuple(sorted(found.items()))


def _values(runs: Sequence[dict[str, str]], key: str) -> str:
    """``5: 1 run, 20: 2 runs``."""
    counts = Counter(s.get(key, "not set") for s in runs)
    return ", ".join(f"{v}: {n} run{'s' * (n != 1)}" for v, n in sorted(counts.items()))
