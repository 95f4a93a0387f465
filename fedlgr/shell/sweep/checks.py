"""What a sweep checks before its first trial trains: every trial's config loads, the objective is a
metric its runs log, the data is there, and a relaunched study's space fits its trials' values."""

from __future__ import annotations

import difflib
import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fedlgr.core.methods import plugin_metrics
from fedlgr.core.metrics import COST_KEYS, SCORE_NAMES, client_key, headline_scores, round_keys
from fedlgr.errors import ConfigError
from fedlgr.shell import config as configs
from fedlgr.shell.config import ExperimentConfig
from fedlgr.shell.sweep.space import CONFIG_KEY, Param, SweepSpec

EXHAUSTIVE = 64  # grids up to this size have every point's config built


def probe_points(spec: SweepSpec) -> list[dict[str, Any]]:
    """The trial points whose configs are checked: every point of a grid of up to
    :data:`EXHAUSTIVE`, else each value of each parameter (a range: its ends) with the others at
    their first, per base config."""
    if spec.sampler == "grid" and spec.n_trials <= EXHAUSTIVE:
        return list(spec.grid_points())
    chooser = next((p for p in spec.params if p.name == CONFIG_KEY), None)
    points = []
    for base in _values(chooser) if chooser else [None]:
        first = {p.name: base if p is chooser else _values(p)[0] for p in spec.params}
        points.append(first)
        for p in spec.params:
            if p is not chooser:
                points += [{**first, p.name: v} for v in _values(p)[1:]]
    return points


def _data_points(spec: SweepSpec) -> list[dict[str, Any]]:
    """A point for each combination of the values that choose the data (``data.path``,
    ``config``), the other parameters at their first value."""
    choosers = [p for p in spec.params if p.name in (CONFIG_KEY, "data.path")]
    first = {p.name: _values(p)[0] for p in spec.params}
    return [
        {**first, **dict(zip([p.name for p in choosers], combo, strict=True))}
        for combo in itertools.product(*(_values(p) for p in choosers))
    ]


def _values(p: Param) -> list[Any]:
    """A grid's or choices' values; a range's ends (as Optuna fits them to its step)."""
    if p.values:
        return list(p.values)
    d = p.distribution()
    return [d.low, d.high]


def _load(spec: SweepSpec, point: dict[str, Any]) -> ExperimentConfig:
    """The config of the trial at ``point``. A ``data.path`` left to the user (``???`` in
    the MANNERS-DB presets) is filled with a placeholder."""
    base, overrides = spec.trial_config_args(point)
    try:
        return configs.load_config(base, overrides)
    except ConfigError as err:
        if "data.path: no value" not in str(err):
            raise ConfigError(f"{spec.path}: trial {point}: {err}") from err
        return configs.load_config(base, [*overrides, "data.path=/path/to/manners-db"])


def tracking_experiment(spec: SweepSpec) -> str:
    """The MLflow experiment its trials' configs name (what a ``tracking.experiment=NAME`` override
    sets), resolved and checked as in a trial's config."""
    return _load(spec, {p.name: _values(p)[0] for p in spec.params}).tracking.experiment


def check_trial_configs(spec: SweepSpec, echo: Callable[[str], None] = print) -> None:
    """Every probed trial's config must load and log the objective's metric, so that a
    typo in a key or in the metric's name fails now rather than in every trial."""
    points = probe_points(spec)
    if spec.sampler == "grid" and spec.n_trials > EXHAUSTIVE:
        echo(
            f"sweep {spec.name}: checking its {spec.n_trials:,}-point grid one parameter at "
            f"a time ({len(points)} configs); the points are built as trials take them"
        )
    logged_by_some = False
    for point in points:
        logged = run_metrics(_load(spec, point))
        if spec.metric in logged:
            logged_by_some = True
            continue
        if logged_by_some:
            raise ConfigError(
                f"{spec.path}: objective.metric: {spec.metric} is not logged by the runs of "
                f"trial {point}"
            )
        apart = ("spread/", "byzantine/")  # a score's spread, the attackers': not examples
        shown = sorted(m for m in logged if "/client" not in m and not m.startswith(apart))
        close = difflib.get_close_matches(spec.metric, shown, n=1)
        hint = f" - did you mean {close[0]}?" if close else ""
        scores = tuple(f"test/{s.name}" for s in headline_scores())
        examples = [m for m in shown if m.endswith(scores)][:4]
        raise ConfigError(
            f"{spec.path}: objective.metric: {spec.metric} is not a metric these runs log"
            f"{hint} (they log e.g. {', '.join(examples)}, mean/cost/cpu_s)"
        )


def run_metrics(config: ExperimentConfig) -> set[str]:
    """The metric names a run of ``config`` can end with, which a sweep's objective reads from
    :meth:`ExperimentResult.final_metrics`; built from the config alone: nothing trains."""
    tasks = list(config.continual.tasks)
    names = {"round/seconds", "round/missing_clients", "round/participants", "round/outliers"}
    names.update(f"spread/test/{s.name}" for s in headline_scores())  # RoundLog.metrics
    # The server's own cost (in-process runtimes), and its evaluation where it runs one.
    server = ("cost/server_cpu_s", "cost/server_wall_s")
    names.update([*server, *(f"mean/{k}" for k in server), "mean/cost/paper_cpu_s"])
    if config.federated.server_evaluates:
        names.update(f"server/test/{m}" for m in SCORE_NAMES)
        names.update(f"server/task/{t}/{m}" for t in tasks for m in SCORE_NAMES)
    plugins = plugin_metrics(config.federated.strategy, config.continual.method)
    attackers = config.federated.faults.byzantine > 0  # their scores apart: byzantine/...
    for key in round_keys(tasks, plugins):
        names.add(key)
        if attackers and key.startswith(("test/", "task/")):
            names.add(f"byzantine/{key}")
        names.update(client_key(key, c) for c in range(config.data.clients))
    for k in range(len(tasks)):
        prefix = f"after_task{k + 1}"
        names.update(f"{prefix}/test/{m}" for m in SCORE_NAMES)
        names.update(f"{prefix}/task/{t}/{m}" for t in tasks[: k + 1] for m in SCORE_NAMES)
        names.update(f"{prefix}/forgetting/{t}/{m}" for t in tasks[:k] for m in SCORE_NAMES)
    names.update(f"mean/{key}" for key in COST_KEYS)
    return names


def check_data_folders(spec: SweepSpec) -> None:
    """Every trial's ``data.path`` must be an existing folder: a sweep refuses to start rather than
    fail each trial (not in ``load_sweep``: a sweep file is checked without its data)."""
    seen: set[Path] = set()
    for point in _data_points(spec):
        base, overrides = spec.trial_config_args(point)
        try:
            path = Path(configs.load_config(base, overrides).data.path)
        except ConfigError as err:  # data.path left unset (???) by a MANNERS-DB preset
            raise ConfigError(f"{spec.path}: {err}") from err
        if path in seen:
            continue
        seen.add(path)
        if not path.is_dir():
            what = "a file, not the dataset folder" if path.exists() else "no such folder"
            raise ConfigError(
                f"{spec.path}: data.path={path}: {what}; set data.path=DIR in the sweep's "
                "overrides or on the command line"
            )


def check_space(study, spec: SweepSpec, where: str) -> None:
    """Refuse a study whose trials drew a parameter from other values than the space now gives (a
    range's ends may move): Optuna fails each new trial whose distribution differs."""
    # lazy: optuna (~1 s), not needed to check a sweep file
    from optuna.distributions import check_distribution_compatibility

    now = spec.search_space()
    before = {}
    for trial in study.get_trials(deepcopy=False):
        for name, distribution in trial.distributions.items():
            before.setdefault(name, distribution)  # Optuna compares with the first
        if now.keys() <= before.keys():
            break
    for name, distribution in now.items():
        if name not in before:
            continue
        try:
            check_distribution_compatibility(before[name], distribution)
        except ValueError:
            raise ConfigError(
                f"study {study.study_name!r} in {where}: space.{name} changed since its "
                f"trials ran: {_shown(before[name])} -> {_shown(distribution)}; Optuna cannot "
                "change a parameter's values inside a study (every new trial would fail): "
                "start a new study with --study NAME (it runs every point of the new space), "
                "or put the old values back"
            ) from None


def _shown(distribution) -> str:
    """A distribution as a sweep file gives it: ``[1, 10, 100]``, ``{low: 1, high: 10}``."""
    # lazy: optuna (~1 s), not needed to check a sweep file
    from optuna.distributions import CategoricalDistribution, IntDistribution

    if isinstance(distribution, CategoricalDistribution):
        return "[" + ", ".join(map(str, distribution.choices)) + "]"
    whole = isinstance(distribution, IntDistribution)
    extra = ", log: true" if distribution.log else ""
    if distribution.step != (1 if whole else None):  # a step other than the default
        extra += f", step: {distribution.step}"
    kind = "whole numbers " if whole else ""
    return f"{kind}{{low: {distribution.low}, high: {distribution.high}{extra}}}"
