"""Which runs a table cell may average: replicates, whose settings differ only in seeds; a seed
repeated counts once (the newest). A run that logged no params is a replicate of its own."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

from fedlgr.shell.report.runs import ReportError, RunRecord
from fedlgr.shell.tracking.context import used_settings

# Runs differing only in these seeds (training; the split into clients) are replicates.
SEEDS = ("seed", "data.seed")
# Settings that change no number a table shows (how a run is recorded, run or cached).
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
    """The settings a cell's runs must share: the params the run uses, but the seeds and
    :data:`IGNORED`; None for a run that logged no params."""
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
    """One run per cell, settings and seeds, the newest; and a line naming the repeats left out."""
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
    """The runs of each cell's best setting by a sweep's ``objective`` (e.g. ``minimize
    test/rmse``), as a sweep has several per cell; every run where ``objective`` is not one."""
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
