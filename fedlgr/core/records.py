"""What one round records: a row of fields per client (results.csv columns, MLflow keys).

The score fields come first (all tasks seen so far, per action too; then each task on
its own in FCL), then what the round cost, then what the plugins measured at task ends.
Both sides agree on them: clients report their scores in this order, the server adds the
costs and turns the rows into a :class:`RoundLog`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from fedlgr.core.data.columns import LABEL_SHORT_NAMES
from fedlgr.core.schedule import ALL

if TYPE_CHECKING:
    from fedlgr.shell.config import ExperimentConfig


@dataclass(frozen=True)
class Field:
    """One number per client per round: its results.csv column and its MLflow key."""

    name: str
    key: str


def _score_fields(name: str, key: str, per_action: bool) -> list[Field]:
    fields = [Field(f"{name}_{m}", f"{key}/{m}") for m in ("loss", "rmse", "pcc")]
    if per_action:
        fields += [
            Field(f"{name}_{m}_{a}", f"{key}/{m}/{a}")
            for m in ("mse", "rmse", "pcc")
            for a in LABEL_SHORT_NAMES
        ]
    return fields


COST_FIELDS = [
    Field("train_loss", "train/loss"),
    Field("train_samples", "train/samples"),
    Field("cpu_s", "cost/cpu_s"),
    Field("wall_s", "cost/wall_s"),
    Field("gpu_util", "cost/gpu_util"),
    Field("gpu_mem_mb", "cost/gpu_mem_mb"),
    Field("gpu_s", "cost/gpu_s"),
    Field("bytes_up", "cost/bytes_up"),
    Field("bytes_down", "cost/bytes_down"),
]


def plugin_fields(plugins) -> list[Field]:
    """What the plugins (or their classes) measure: ``<plugin>_<name>``, MLflow
    ``<plugin>/<name>``."""
    return [Field(f"{p.name}_{m}", f"{p.name}/{m}") for p in plugins for m in p.metric_names]


def method_fields(config: ExperimentConfig) -> list[Field]:
    """What the method's client plugins measure, from their classes (every client has the
    same kinds): the strategy's and the continual-learning method's."""
    from fedlgr.core.continual import continual_plugin_types
    from fedlgr.core.methods import STRATEGIES

    strategy = STRATEGIES[config.federated.strategy].load()
    return plugin_fields([*strategy.client_plugin_types, *continual_plugin_types(config.continual)])


def make_fields(tasks: list[str]) -> list[Field]:
    """``test_*``: all seen tasks' test scenes (the whole test set in FL), per action too;
    ``task_<name>_*``: each task's test scenes (FCL only); then the costs."""
    fields = _score_fields("test", "test", per_action=True)
    if tasks != [ALL]:
        for task in tasks:
            fields += _score_fields(f"task_{task}", f"task/{task}", per_action=False)
    return fields + COST_FIELDS


def client_key(key: str, client: int) -> str:
    """The MLflow key of ``key`` for one client: ``test/pcc/vacuum`` ->
    ``test/client3/pcc/vacuum`` (the family first, then the client)."""
    family, _, rest = key.partition("/")
    return f"{family}/client{client}/{rest}"


@dataclass
class RoundLog:
    """Per-client rows of one round (after the collective: all clients)."""

    round: int
    task: str
    fields: list[Field]
    table: np.ndarray  # (clients, len(fields))
    seconds: float
    missing: tuple[int, ...] = ()  # clients that did not report (robots that dropped out)
    # The server's own figures: its cost (cost/server_*), its evaluation (server/test/*).
    server: dict[str, float] = field(default_factory=dict)
    # federated.server_eval: the initial model's scores, before round 1 (step 0).
    initial: dict[str, float] = field(default_factory=dict)

    @property
    def column_names(self) -> list[str]:
        return [f.name for f in self.fields]

    def column(self, name: str) -> np.ndarray:
        return self.table[:, self.column_names.index(name)]

    def mean(self, name: str) -> float | None:
        column = self.column(name)
        return None if np.isnan(column).all() else float(np.nanmean(column))

    def rows(self) -> list[dict[str, object]]:
        out = []
        for client, values in enumerate(self.table):
            row: dict[str, object] = {"round": self.round, "task": self.task, "client": client}
            row.update(
                {
                    f.name: None if math.isnan(v) else float(v)
                    for f, v in zip(self.fields, values, strict=True)
                }
            )
            out.append(row)
        return out

    def metrics(self) -> dict[str, float]:
        """MLflow metrics of this round: means over clients (``test/rmse``) and per-client
        values under the same family (``test/client3/rmse``, ``cost/client3/cpu_s``), so
        that MLflow's charts group a family's mean with its clients."""
        out: dict[str, float] = {"round/seconds": self.seconds, **self.server}
        if self.missing:
            out["round/missing_clients"] = float(len(self.missing))
        for f, column in zip(self.fields, self.table.T, strict=True):
            if not np.isnan(column).all():
                out[f.key] = float(np.nanmean(column))
            for client, value in enumerate(column):
                if not math.isnan(value):
                    out[client_key(f.key, client)] = float(value)
        return out
