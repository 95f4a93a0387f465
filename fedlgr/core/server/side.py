"""The server side of a federation: the global tensors, aggregation, the strategy's server
step, and the round's record.

:class:`ServerSide` needs no data and no client: it builds the run's initial model to
know the shared tensors, aggregates what the clients upload (sample-weighted mean, in
float64, then ``Strategy.server_update``) and turns the clients' reports into a
:class:`RoundLog` row per client - a client that did not report (a robot that dropped
out) gets a row of NaN and is named in ``RoundLog.missing``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import torch

from fedlgr.core.messages import (
    EvaluateRes,
    RoundPlan,
    TrainIns,
    TrainRes,
    Weights,
    check_shared,
    nbytes,
)
from fedlgr.core.records import RoundLog, make_fields, method_fields
from fedlgr.core.schedule import ALL
from fedlgr.core.scope import SCOPE_PREFIX, initial_scholar, parameter_keys, shared_keys
from fedlgr.core.server.aggregate import finish_mean, weighted_sum
from fedlgr.core.strategies import build_strategy
from fedlgr.shell.config import ExperimentConfig
from fedlgr.shell.run.checkpoint import to_device


class ServerSide:
    def __init__(self, config: ExperimentConfig):
        cfg = config
        self.config = config
        self.tasks = list(cfg.continual.tasks) or [ALL]
        self.strategy = build_strategy(cfg.federated)
        initial = initial_scholar(cfg)
        self.keys = shared_keys(initial, cfg.federated.scope, self.strategy)
        self.prefix = SCOPE_PREFIX[cfg.federated.scope]
        self.strategy.bind(self.keys, parameter_keys(initial))
        state = initial.state_dict()
        self.global_weights: Weights = {k: state[k].detach().clone() for k in self.keys}
        self.initial_bytes = nbytes(self.global_weights)
        self.plugin_fields = method_fields(cfg)
        self.fields = make_fields(self.tasks) + self.plugin_fields

    def to(self, device: torch.device) -> ServerSide:
        self.global_weights = {k: v.to(device) for k, v in self.global_weights.items()}
        return self

    def train_ins(self, plan: RoundPlan, holds_global: bool = True) -> TrainIns:
        """The round's training message; the global tensors go along to a client that does
        not hold them yet (round 1, or a robot that missed the last round)."""
        return TrainIns(plan, None if holds_global else self.global_weights)

    def bytes_down(self, round_: int) -> int:
        """What a client that took part in every round downloads in round ``round_``: the
        new global tensors, and in round 1 the initial ones too."""
        return nbytes(self.global_weights) + (self.initial_bytes if round_ == 1 else 0)

    # ------------------------------------------------------------------ aggregation

    def sums(self, results: Iterable[TrainRes]) -> tuple[Weights, float]:
        """Sample-weighted sums of the uploads (float64), and the sum of the weights."""
        results = list(results)
        for r in results:
            check_shared(r.weights, self.keys, f"client {r.client}'s upload", self.prefix)
        return weighted_sum(((r.n_samples, r.weights) for r in results), self.keys)

    def update(self, sums: Weights, total: float) -> None:
        """The next global tensors from the sums of every upload."""
        mean = finish_mean(sums, total, like=self.global_weights)
        self.global_weights = self.strategy.server_update(self.global_weights, mean)

    def aggregate(self, results: Iterable[TrainRes]) -> None:
        self.update(*self.sums(results))

    # ------------------------------------------------------------------ the record

    def row(
        self, trained: TrainRes, evaluated: EvaluateRes, bytes_up: int, bytes_down: int
    ) -> list[float]:
        """One client's row of the round: its scores, its costs, its plugins' figures."""
        usage = trained.usage if evaluated.usage is None else trained.usage + evaluated.usage
        costs = [
            trained.loss,
            trained.samples,
            usage.cpu_s,
            usage.wall_s,
            math.nan if usage.gpu_util is None else usage.gpu_util,
            math.nan if usage.gpu_mem_mb is None else usage.gpu_mem_mb,
            math.nan if usage.gpu_s is None else usage.gpu_s,
            bytes_up,
            bytes_down,
        ]
        measured = [evaluated.figures.get(f.name, math.nan) for f in self.plugin_fields]
        return list(evaluated.scores) + costs + measured

    def table(self, rows: dict[int, list[float]], fill: float = math.nan) -> torch.Tensor:
        """All clients' rows (clients x fields, float64); ``fill`` for the absent ones."""
        table = torch.full((self.config.data.clients, len(self.fields)), fill, dtype=torch.float64)
        for client, row in rows.items():
            table[client] = torch.tensor(row, dtype=torch.float64)
        return table

    def round_log(
        self, plan: RoundPlan, table: torch.Tensor | np.ndarray, seconds: float, missing=()
    ) -> RoundLog:
        table = table.numpy() if isinstance(table, torch.Tensor) else table
        return RoundLog(plan.round, self.tasks[plan.task], self.fields, table, seconds, missing)

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict:
        return {"global": self.global_weights, "strategy": self.strategy.state_dict()}

    def load_state_dict(self, state: dict, device: torch.device) -> None:
        self.global_weights = {k: v.to(device) for k, v in state["global"].items()}
        self.strategy.load_state_dict(to_device(state["strategy"], device))
