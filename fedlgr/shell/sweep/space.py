"""A sweep as the code holds it once its file is read: the settings it searches (:class:`Param`) and
what it is run with (:class:`SweepSpec`), down to each trial's config file and overrides."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fedlgr.errors import ConfigError
from fedlgr.shell.checks.paths import not_a_file
from fedlgr.shell.config import CONF_DIR

CONFIG_KEY = "config"  # the space key that chooses the base config file


@dataclass(frozen=True)
class Param:
    """One searched setting: a grid (``values``), a range (``low``/``high``) or categorical
    choices (``values`` with ``categorical``) for TPE."""

    name: str
    values: tuple[Any, ...] = ()
    low: float | None = None
    high: float | None = None
    log: bool = False
    step: float | None = None
    categorical: bool = False

    @property
    def is_grid(self) -> bool:
        return bool(self.values) and not self.categorical

    @property
    def whole(self) -> bool:
        """A range of whole numbers: whole ends and step (Optuna's IntDistribution)."""
        whole_step = self.step is None or float(self.step).is_integer()
        return isinstance(self.low, int) and isinstance(self.high, int) and whole_step

    def distribution(self):
        """Optuna's distribution for this parameter."""
        # lazy: optuna (~1 s); a grid's sweep file is read and checked without it
        from optuna.distributions import (
            CategoricalDistribution,
            FloatDistribution,
            IntDistribution,
        )

        if self.values:
            return CategoricalDistribution(list(self.values))
        if self.whole:
            return IntDistribution(self.low, self.high, log=self.log, step=int(self.step or 1))
        return FloatDistribution(float(self.low), float(self.high), log=self.log, step=self.step)

    def suggest(self, trial) -> Any:
        """Draw this parameter for an Optuna trial (grid points come from GridSampler)."""
        d = self.distribution()
        if self.values:
            return trial.suggest_categorical(self.name, d.choices)
        suggest = trial.suggest_int if self.whole else trial.suggest_float
        return suggest(self.name, d.low, d.high, step=d.step, log=d.log)

    def size(self) -> int | None:
        """How many distinct values the parameter can take; None for a continuous range."""
        if self.values:
            return len(self.values)
        d = self.distribution()  # Optuna has fitted high to the step
        if self.whole:
            return (d.high - d.low) // d.step + 1
        return None if d.step is None else round((d.high - d.low) / d.step) + 1


@dataclass(frozen=True)
class SweepSpec:
    name: str
    path: Path | None
    base: Path | None
    params: tuple[Param, ...]
    metric: str = "test/rmse"
    direction: str = "minimize"
    sampler: str = "grid"
    trials: int | None = None  # TPE: how many; grid: the grid's size
    pruner: str = "none"
    prune_warmup_rounds: int = 2
    seed: int = 0
    overrides: tuple[str, ...] = ()
    experiment: str = ""
    description: str = ""
    heartbeat_s: int = 30  # a trial whose worker is silent for 2 heartbeats is retried
    failures_in_a_row: int = 3  # the sweep stops once this many trials in a row failed

    @property
    def grid(self) -> dict[str, list[Any]]:
        """GridSampler's search space (grid sweeps)."""
        return {p.name: list(p.values) for p in self.params}

    def grid_points(self) -> Iterator[dict[str, Any]]:
        """Every point of the grid, built one at a time (a grid can hold millions)."""
        names = [p.name for p in self.params]
        for combo in itertools.product(*(p.values for p in self.params)):
            yield dict(zip(names, combo, strict=True))

    def space_size(self) -> int | None:
        """How many distinct points the space holds; None when a range is continuous."""
        sizes = [p.size() for p in self.params]
        return None if None in sizes else math.prod(sizes)

    @property
    def n_trials(self) -> int:
        if self.sampler == "grid":
            return math.prod(len(p.values) for p in self.params)
        return int(self.trials or 0)

    def search_space(self) -> dict[str, Any]:
        """Optuna distributions per parameter (what the trials are drawn from)."""
        return {p.name: p.distribution() for p in self.params}

    def trial_config_args(self, params: dict[str, Any]) -> tuple[Path | None, list[str]]:
        """The base config file and ``key=value`` overrides of a trial with ``params``."""
        base = self.base
        overrides = list(self.overrides)
        for name, value in params.items():
            if name == CONFIG_KEY:
                base = resolve_config(value, self.path)
            else:
                overrides.append(f"{name}={_as_override(value)}")
        return base, overrides


def _as_override(value: Any) -> str:
    if value is None:  # a grid's null (YAML): "unset", e.g. continual.lgr.train_blocks
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_as_override(v) for v in value) + "]"
    return str(value)


def resolve_config(name: str | Path, sweep_path: Path | None = None) -> Path:
    """A base config named relative to ``conf/`` (``experiment/table1/clients2_noaug.yaml``),
    to the sweep file, or as a path."""
    candidates = (Path(name), CONF_DIR / name, *([sweep_path.parent / name] if sweep_path else []))
    for candidate in candidates:
        if candidate.is_file():
            return candidate.resolve()
    for candidate in candidates:  # a FIFO or a dangling link is there: say what it is
        if why := not_a_file(candidate):
            raise ConfigError(f"config {name}: {candidate} is {why}")
    raise ConfigError(f"config {name}: no such file (looked in ., conf/ and next to the sweep)")
