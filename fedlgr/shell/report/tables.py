"""The paper's Tables I-IV as data, built from run records (pure: no MLflow, no files): each
method's scores, the best two marked, and its costs, FedRoot's reduction against the full model."""

from __future__ import annotations

import math
import re
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field

from fedlgr.core.methods import in_paper
from fedlgr.core.metrics import COSTS as METRIC_COSTS
from fedlgr.core.metrics import SCORES as METRIC_SCORES
from fedlgr.shell.config import FCL_METHODS, METHODS, short_setting
from fedlgr.shell.report.runs import RunRecord

PAPER_CLIENTS = (2, 10)
BLOCKS = ((False, "W/O augmentation"), (True, "W/ augmentation"))
# The server process's CPU over clients x rounds: what the paper's Tables III/IV measured
# (docs/methods.md, "Table III and IV: what the paper measured"); a row only where runs have it.
PAPER_CPU = "mean/cost/paper_cpu_s"
# Row label, run-level metric, scale and decimals of every cost with a report label; the
# paper's CPU after the CPU.
COSTS = [(c.label, f"mean/{c.key}", c.scale, c.decimals) for c in METRIC_COSTS if c.label]
COSTS.insert(
    [m for _, m, _, _ in COSTS].index("mean/cost/cpu_s") + 1,
    ("CPU usage, the paper's way (s)", PAPER_CPU, 1.0, 2),
)
NUMBERS = {"table1": "I", "table2": "II", "table3": "III", "table4": "IV"}


@dataclass(frozen=True)
class Column:
    key: str  # the CSV header, e.g. "2c/after_task1/test/loss"
    header: tuple[str, ...]  # top level first, e.g. ("2 clients", "After Task 1", "Loss")
    lower_is_better: bool | None = None  # None: the direction is given per row
    group: str = ""  # columns of one group sit between vertical rules in LaTeX
    reduces: str | None = None  # cost tables: the full-model method this one is compared to


@dataclass
class Cell:
    value: float | None = None
    decimals: int = 3
    runs: int = 0  # runs averaged into the value
    mark: str = ""  # "best", "second" or ""
    reduction: float | None = None  # % saved against the full-model counterpart
    std: float | None = None  # sample standard deviation over the runs (2 runs or more)
    won: str = ""  # a sweep's cell: the swept values of the best trial, e.g. "ewc.lambda_=1000"

    def shown(self) -> str:
        return "" if self.value is None else f"{self.value:.{self.decimals}f}"

    def detail(self) -> str:
        """What follows the number: `` (± 0.012, n=3)`` over several runs, `` (lr_top=0.01)``
        for a sweep's best trial, else nothing."""
        std = "" if self.std is None else f"± {self.std:.{self.decimals}f}, n={self.runs}"
        parts = [p for p in (std, self.won) if p]
        return f" ({'; '.join(parts)})" if parts and self.value is not None else ""


@dataclass
class Block:
    title: str
    rows: list[tuple[str, list[Cell]]]


@dataclass
class Table:
    name: str  # file stem: table1 ... table4
    caption: str
    row_header: str  # "Method" or "Metric"
    block_header: str  # what the blocks are, as a CSV column: "augmentation", "setting"
    columns: list[Column]
    blocks: list[Block]
    runs: int  # runs the table is built from
    notes: list[str] = field(default_factory=list)
    row_direction: bool | None = None  # cost tables: every row is lower-is-better

    @property
    def number(self) -> str:
        return NUMBERS.get(self.name, self.name)


# --------------------------------------------------------------------------- marking


def mark_best(values: Sequence[float | None], lower_is_better: bool, decimals: int) -> list[str]:
    """``best`` for the best value, ``second`` for the second-best, "" otherwise; compared as
    shown (rounded to ``decimals``), so equal-looking values get the same mark."""
    shown = [
        float(f"{v:.{decimals}f}") if v is not None and math.isfinite(v) else None for v in values
    ]
    ranked = sorted({v for v in shown if v is not None}, reverse=not lower_is_better)
    best, second = [*ranked, None, None][:2]
    return [
        "" if v is None else "best" if v == best else "second" if v == second else "" for v in shown
    ]


def mark_lower_of_pair(full: float | None, root: float | None, decimals: int) -> list[str]:
    """Tables III/IV: ``best`` on the lower of a full-model / FedRoot pair of costs; no mark
    when one is missing or both look the same."""
    if full is None or root is None:
        return ["", ""]
    marks = mark_best([full, root], lower_is_better=True, decimals=decimals)
    return ["", ""] if marks == ["best", "best"] else [m if m == "best" else "" for m in marks]


def reduction_percent(full: float | None, root: float | None) -> float | None:
    """How much less the FedRoot variant costs than its full-model counterpart, in % of the
    latter (negative: it costs more); ``None`` if either is missing or the full cost is 0."""
    if full is None or root is None or not (math.isfinite(full) and math.isfinite(root)):
        return None
    return None if full <= 0 else 100.0 * (full - root) / full


# --------------------------------------------------------------------------- methods


def method_order(benchmark: str, records: Sequence[RunRecord]) -> list[str]:
    """The table's rows: the paper's methods in ``fedlgr.core.methods`` order, then the -FT
    baselines, other and unknown methods that have runs."""
    known = list(METHODS if benchmark == "FL" else FCL_METHODS)
    paper = [m for m in known if not m.endswith("-FT") and in_paper(m)]
    with_runs = {r.method for r in records if r.benchmark == benchmark}
    extra = [m for m in known if m not in paper and m in with_runs]
    return [*paper, *extra, *sorted(with_runs - set(known))]


def full_counterpart(method: str) -> str | None:
    """FedRootAvg -> FedAvg, FedRoot-EWC -> FedAvg-EWC; None for full-model methods and for
    FedLGR (its replay needs the local top, so the paper has no full-model FedLGR)."""
    for table in (METHODS, FCL_METHODS):
        if method in table:
            strategy, scope, continual = table[method]
            if scope != "root":
                return None
            match = [n for n, s in table.items() if s == (strategy, "full", continual)]
            return match[0] if match else None
    return None


def cost_columns_order(methods: Sequence[str]) -> list[str]:
    """Each full-model method followed by its FedRoot variant, as in Tables III/IV."""
    partner = {full_counterpart(m): m for m in methods if full_counterpart(m) in methods}
    paired = set(partner.values())
    return [x for m in methods if m not in paired for x in (m, partner.get(m)) if x]


# --------------------------------------------------------------------------- cells


def setting_label(setting: tuple[int, bool]) -> str:
    """``2 clients, W/O augmentation``."""
    clients, augmented = setting
    return f"{clients} clients, {dict(BLOCKS)[augmented]}"


def group_runs(records: Sequence[RunRecord]) -> dict[tuple[str, int, bool], list[RunRecord]]:
    """Runs per cell: (method, clients, augmentation)."""
    cells: dict[tuple[str, int, bool], list[RunRecord]] = {}
    for r in records:
        cells.setdefault((r.method, r.clients, r.augmentation), []).append(r)
    return cells


def mean_cell(runs: Sequence[RunRecord], metric: str, decimals: int, scale: float = 1.0) -> Cell:
    """The mean over ``runs`` (seeds, repeats), its standard deviation from two runs on,
    and for a sweep's best trial the values it won with."""
    values = [scale * v for v in (r.value(metric) for r in runs) if v is not None]
    mean = sum(values) / len(values) if values else None
    std = statistics.stdev(values) if len(values) > 1 else None
    swept = runs[0].swept if runs and all(r.swept == runs[0].swept for r in runs) else {}
    won = " ".join(f"{short_setting(k)}={v}" for k, v in swept.items())
    return Cell(mean, decimals, len(values), std=std, won=won)


def after_tasks(records: Sequence[RunRecord]) -> list[int]:
    """Task numbers k with ``after_task{k}/test/*`` metrics (at least the paper's 1 and 2)."""
    found = {
        int(m.group(1))
        for r in records
        for key in r.metrics
        if (m := re.fullmatch(r"after_task(\d+)/test/\w+", key))
    }
    return sorted(found | {1, 2})


# --------------------------------------------------------------------------- tables


def score_table(runs: Sequence[RunRecord], benchmark: str, source: str) -> Table:
    """Table I (``benchmark="FL"``) or Table II (``"FCL"``) of the benchmark's ``runs``."""
    fl = benchmark == "FL"
    clients = sorted(set(PAPER_CLIENTS) | {r.clients for r in runs})
    stages = (
        [("", ())] if fl else [(f"after_task{k}/", (f"After Task {k}",)) for k in after_tasks(runs)]
    )
    columns, metrics = [], []
    for c in clients:
        for prefix, stage in stages:
            for s in METRIC_SCORES:  # headed "Loss", "RMSE"
                metric = f"{prefix}test/{s.name}"
                header = (f"{c} clients", *stage, s.label[:1].upper() + s.label[1:])
                group = " · ".join(header[:-1])
                columns.append(Column(f"{c}c/{metric}", header, not s.higher_is_better, group))
                metrics.append((c, metric))
    cells = group_runs(runs)
    blocks = []
    for augmented, title in BLOCKS:
        if not any(r.augmentation == augmented for r in runs):
            continue  # nothing ran in this setting: no block of dashes
        rows = [
            (m, [mean_cell(cells.get((m, c, augmented), []), metric, 3) for c, metric in metrics])
            for m in method_order(benchmark, runs)
        ]
        for j, column in enumerate(columns):
            column_cells = [row[j] for _, row in rows]
            marks = mark_best([x.value for x in column_cells], bool(column.lower_is_better), 3)
            for cell, mark in zip(column_cells, marks, strict=True):
                cell.mark = mark
        blocks.append(Block(title, rows))
    caption = (
        f"Federated Learning results on the test set (final round; {_scores_named()} "
        "averaged over the 8 actions and the clients)."
        if fl
        else "Federated Continual Learning results: 'After Task 1' on the test scenes of "
        "Task 1, 'After Task 2' on the test scenes of both tasks."
    )
    notes = [
        "**Bold**: best, [bracketed]: second-best value of a column within a block; "
        "▼ lower is better, ▲ higher is better; — no finished runs.",
        _runs_note(runs, blocks, source),
    ]
    name = "table1" if fl else "table2"
    return Table(name, caption, "Method", "augmentation", columns, blocks, len(runs), notes)


def _scores_named() -> str:
    """``loss, RMSE and PCC``: the scores' names as a caption says them."""
    names = [s.label for s in METRIC_SCORES]
    return ", ".join(names[:-1]) + f" and {names[-1]}"


def cost_table(runs: Sequence[RunRecord], benchmark: str, source: str) -> Table:
    """Table III (``benchmark="FL"``) or Table IV (``"FCL"``) of the benchmark's ``runs``."""
    methods = cost_columns_order(method_order(benchmark, runs))
    reduces = {m: full for m in methods if (full := full_counterpart(m)) in methods}
    columns = [Column(m, (m,), None, reduces.get(m, m), reduces.get(m)) for m in methods]
    cells = group_runs(runs)
    settings = sorted({(r.clients, r.augmentation) for r in runs})
    blocks = []
    for clients, augmented in settings:
        rows = []
        for label, metric, scale, decimals in COSTS:
            row = [
                mean_cell(cells.get((m, clients, augmented), []), metric, decimals, scale)
                for m in methods
            ]
            by_method = dict(zip(methods, row, strict=True))
            for column, cell in zip(columns, row, strict=True):
                if column.reduces is None:
                    continue
                full = by_method[column.reduces]
                cell.reduction = reduction_percent(full.value, cell.value)
                full.mark, cell.mark = mark_lower_of_pair(full.value, cell.value, decimals)
            if metric == PAPER_CPU and all(c.value is None for c in row):
                continue  # runs made without the server's own measure
            rows.append((label, row))
        blocks.append(Block(setting_label((clients, augmented)), rows))
    name = "table3" if benchmark == "FL" else "table4"
    kind = "Federated Learning" if benchmark == "FL" else "Federated Continual Learning"
    caption = (
        f"Average CPU usage (s) and GPU usage (%) per client, per aggregation round for "
        f"{kind} experiments (also wall time and upload)."
    )
    notes = [
        "Costs per client per round, averaged over all rounds and clients (`mean/cost/*`); "
        "the paper's way: the server's CPU (aggregation, server evaluation) over clients x "
        "rounds, as the paper's code measured it (`mean/cost/paper_cpu_s`). "
        "**Bold**: the lower of a full-model / FedRoot pair; (▼ x%) the FedRoot variant's "
        "reduction against its full-model counterpart (▲: an increase); — no runs, or not "
        "measured (GPU usage needs an NVIDIA GPU).",
        _runs_note(runs, blocks, source),
    ]
    return Table(
        name, caption, "Metric", "setting", columns, blocks, len(runs), notes, row_direction=True
    )


def build_tables(
    records: Sequence[RunRecord], source: str, notes: Sequence[str] = ()
) -> list[Table]:
    """Tables I-IV, each only if its benchmark (FL or FCL) has runs; ``notes`` (what the
    report says once: the study reported, repeats left out) end each table."""
    tables = [
        build(runs, benchmark, source)
        for build in (score_table, cost_table)
        for benchmark in ("FL", "FCL")
        if (runs := [r for r in records if r.benchmark == benchmark])
    ]
    for table in tables:
        table.notes += notes
    return tables


def _runs_note(runs: Sequence[RunRecord], blocks: Sequence[Block], source: str) -> str:
    cells = [c for b in blocks for _, row in b.rows for c in row]
    counts = sorted({c.runs for c in cells if c.value is not None}) or [0]
    low, high = counts[0], counts[-1]
    each = f"{low} to {high} runs" if low != high else f"{low} run" + "s" * (low != 1)
    return (
        f"Built from {len(runs)} finished run{'s' * (len(runs) != 1)} of {source}; "
        f"each value is the mean over its runs ({each} per value), with ± the standard "
        "deviation and n the runs where there are several; a sweep's cell names the swept "
        "values of its best trial."
    )
