"""The report's PNGs (matplotlib, Agg backend): per-round curves, forgetting and costs.

A line or bar per method (the mean over its runs), per setting; a plot without data is not drawn.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from pathlib import Path

from fedlgr.core.metrics import headline_scores
from fedlgr.shell.report.runs import RunRecord
from fedlgr.shell.report.tables import method_order, setting_label

Setting = tuple[int, bool]  # (clients, augmentation)
Series = dict[Setting, dict[str, list[tuple[int, float]]]]  # setting -> method -> points
Bars = dict[Setting, dict[str, float]]  # setting -> method -> value


def write_plots(
    records: Sequence[RunRecord], histories: dict[str, dict[str, list]], out: Path
) -> list[str]:
    """Every plot that has data; ``histories[metric][run_id]`` = [(round, value), ...] of
    each headline score ``test/{name}``. Returns the file names written."""
    written = []
    for benchmark in ("FL", "FCL"):
        runs = [r for r in records if r.benchmark == benchmark]
        if not runs:
            continue
        curves = {
            f"test {s.label}": mean_curves(runs, histories.get(f"test/{s.name}", {}))
            for s in headline_scores()
        }
        plots = {f"{benchmark.lower()}_curves.png": (curves_plot, "test scores per round", curves)}
        if benchmark == "FCL":
            bars = {
                f"forgetting of Task 1, {s.label}": mean_bars(runs, task1_forgetting, s.name)
                for s in headline_scores()
            }
            title = "forgetting of Task 1 after the last task (positive = forgotten)"
            plots["forgetting.png"] = (bar_plot, title, bars)
        costs = {
            "CPU s per client per round": mean_bars(runs, RunRecord.value, "mean/cost/cpu_s"),
            "GPU % per client per round": mean_bars(runs, RunRecord.value, "mean/cost/gpu_util"),
        }
        plots[f"{benchmark.lower()}_costs.png"] = (bar_plot, "costs per client per round", costs)
        order = method_order(benchmark, runs)
        for name, (draw, title, panels) in plots.items():
            if draw(out / name, f"{benchmark}: {title}", panels, order):
                written.append(name)
    return written


def mean_curves(runs: Sequence[RunRecord], history: dict[str, list]) -> Series:
    """Per setting and method, the mean over runs of each round's value."""
    sums: dict[Setting, dict[str, dict[int, list[float]]]] = {}
    for r in runs:
        for step, value in history.get(r.run_id, []):
            per_step = sums.setdefault((r.clients, r.augmentation), {})
            per_step.setdefault(r.method, {}).setdefault(step, []).append(value)
    return {
        s: {m: [(k, sum(v) / len(v)) for k, v in sorted(steps.items())] for m, steps in ms.items()}
        for s, ms in sums.items()
    }


def mean_bars(
    runs: Sequence[RunRecord], read: Callable[[RunRecord, str], float | None], metric: str
) -> Bars:
    """Per setting and method, the mean of ``read(run, metric)`` over the runs that have it."""
    values: dict[Setting, dict[str, list[float]]] = {}
    for r in runs:
        v = read(r, metric)
        if v is not None:
            values.setdefault((r.clients, r.augmentation), {}).setdefault(r.method, []).append(v)
    return {s: {m: sum(v) / len(v) for m, v in ms.items()} for s, ms in values.items()}


def task1_forgetting(run: RunRecord, metric: str) -> float | None:
    """``after_task{K}/forgetting/{task 1}/{metric}`` for the largest K the run logged."""
    first = [
        m.group(1)
        for key in run.metrics
        if (m := re.fullmatch(r"after_task1/task/([^/]+)/\w+", key))
    ]
    if not first:
        return None
    pattern = rf"after_task(\d+)/forgetting/{re.escape(first[0])}/{metric}"
    found = [(int(m.group(1)), key) for key in run.metrics if (m := re.fullmatch(pattern, key))]
    return run.value(max(found)[1]) if found else None


def pyplot():
    """matplotlib's pyplot, drawing to files only."""
    import matplotlib  # lazy: matplotlib (seconds), only when a report draws its plots

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: as matplotlib, once its backend is chosen

    return plt


def curves_plot(path: Path, title: str, panels: dict[str, Series], order: list[str]) -> bool:
    """A row per setting, a column per metric, a line per method."""
    settings = sorted({s for series in panels.values() for s in series})
    if not settings:
        return False
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator  # lazy: matplotlib, as in pyplot

    colors = {m: f"C{i % 10}" for i, m in enumerate(order)}
    size = (4.5 * len(panels) + 1.8, 3.0 * len(settings))
    fig, axes = plt.subplots(
        len(settings), len(panels), figsize=size, squeeze=False, constrained_layout=True
    )
    lines = {}
    for i, setting in enumerate(settings):
        for j, (label, series) in enumerate(panels.items()):
            ax, rounds = axes[i][j], set()
            for method in order:
                points = series.get(setting, {}).get(method)
                if points:
                    steps, values = zip(*points, strict=True)
                    (lines[method],) = ax.plot(steps, values, marker="o", color=colors[method])
                    rounds.update(steps)
            ax.set_title(setting_label(setting), fontsize=9)
            ax.set_xlabel("round")
            ax.set_ylabel(label)
            if 0 < len(rounds) <= 12:
                ax.set_xticks(sorted(rounds))
            else:
                ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.grid(alpha=0.3)
    methods = [m for m in order if m in lines]
    fig.legend([lines[m] for m in methods], methods, loc="outside right upper", fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def bar_plot(path: Path, title: str, panels: dict[str, Bars], order: list[str]) -> bool:
    """A panel per metric that has data; methods along x, a bar per setting."""
    panels = {label: bars for label, bars in panels.items() if any(bars.values())}
    if not panels:
        return False
    plt = pyplot()
    methods = [m for m in order if any(m in b for bars in panels.values() for b in bars.values())]
    size = (max(6.0, 0.8 * len(methods) + 2), 3.4 * len(panels))
    fig, axes = plt.subplots(len(panels), 1, figsize=size, squeeze=False, constrained_layout=True)
    for ax, (label, bars) in zip(axes[:, 0], panels.items(), strict=True):
        settings = sorted(bars)
        width = 0.8 / len(settings)
        for k, setting in enumerate(settings):
            xs = [i + (k - (len(settings) - 1) / 2) * width for i in range(len(methods))]
            values = [bars[setting].get(m, float("nan")) for m in methods]
            ax.bar(xs, values, width, label=setting_label(setting))
        ax.set_xticks(range(len(methods)), methods, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel(label)
        ax.axhline(0, color="0.3", linewidth=0.6)
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True
