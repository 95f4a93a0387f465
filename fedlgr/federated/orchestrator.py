"""The Fabric-based federated round orchestrator (SPEC 4.3).

``setup`` -> ``fabric.launch(main)`` -> an explicit round loop. In each round every client
trains its local model for E epochs on its shard, uploads the tensors its strategy and
scope share, the server aggregates (sample-weighted mean, then the strategy's server
update), every client downloads the new global tensors and evaluates its own model on the
shared test set. All client and server state lives in memory (see ``Client.state_dict``).

By default all clients run in one process on one device. With ``runtime.devices=N`` (and
``runtime.num_nodes``) the clients are dealt round-robin to the processes, each process
trains its own, and aggregation is one weighted ``all_reduce``; per-client metrics are
reduced to rank 0, which alone logs. Seeds are per client, so both modes compute the same
numbers.
"""

from __future__ import annotations

import copy
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from fedlgr.config import ExperimentConfig
from fedlgr.data.augment import Augment, SceneBatches, normalize
from fedlgr.data.columns import LABEL_SHORT_NAMES
from fedlgr.data.dataset import Scenes
from fedlgr.data.splits import FederatedSplit
from fedlgr.federated.aggregate import finish_mean, weighted_sum
from fedlgr.federated.client import Client, LocalStats, train_locally
from fedlgr.federated.evaluation import evaluate
from fedlgr.federated.plugins import LocalContext
from fedlgr.federated.scope import nbytes, parameter_keys, shared_keys
from fedlgr.federated.strategies import STRATEGIES, FedOpt
from fedlgr.models.scholar import build_scholar
from fedlgr.tracking.metrics import RegressionScores
from fedlgr.tracking.resources import Usage, measure

# One row of numbers per client per round; the order is the layout of the collective.
COST_FIELDS = (
    "train_loss",
    "train_samples",
    "cpu_s",
    "wall_s",
    "gpu_util",
    "gpu_mem_mb",
    "bytes_up",
    "bytes_down",
)
SCORE_FIELDS = (
    "test_loss",
    "test_rmse",
    "test_pcc",
    *(f"test_mse_{a}" for a in LABEL_SHORT_NAMES),
    *(f"test_rmse_{a}" for a in LABEL_SHORT_NAMES),
    *(f"test_pcc_{a}" for a in LABEL_SHORT_NAMES),
)
FIELDS = (*SCORE_FIELDS, *COST_FIELDS)


def score_row(scores: RegressionScores) -> list[float]:
    return [
        scores.loss,
        scores.mean_rmse,
        scores.mean_pcc,
        *scores.mse.tolist(),
        *scores.rmse.tolist(),
        *scores.pcc.tolist(),
    ]


def client_seed(seed: int, client: int) -> int:
    return int(np.random.SeedSequence([seed, client]).generate_state(1)[0])


@dataclass
class RoundLog:
    """Per-client rows of one round (after the collective: all clients)."""

    round: int
    table: np.ndarray  # (clients, len(FIELDS))
    seconds: float

    def rows(self) -> list[dict[str, object]]:
        out = []
        for client, values in enumerate(self.table):
            row: dict[str, object] = {"round": self.round, "client": client}
            row.update(
                {
                    f: (None if math.isnan(v) else float(v))
                    for f, v in zip(FIELDS, values, strict=True)
                }
            )
            out.append(row)
        return out

    def mean(self, name: str) -> float | None:
        column = self.table[:, FIELDS.index(name)]
        return None if np.isnan(column).all() else float(np.nanmean(column))

    def metrics(self) -> dict[str, float]:
        """MLflow metrics of this round: means over clients and per-client values."""
        out: dict[str, float] = {"round/seconds": self.seconds}
        for j, name in enumerate(FIELDS):
            key = _metric_key(name)
            column = self.table[:, j]
            if not np.isnan(column).all():
                out[key] = float(np.nanmean(column))
            for client, value in enumerate(column):
                if not math.isnan(value):
                    out[f"client{client}/{key}"] = float(value)
        return out


def _metric_key(field_name: str) -> str:
    """``test_rmse_vacuum`` -> ``test/rmse/vacuum``; ``cpu_s`` -> ``cost/cpu_s``."""
    if field_name.startswith("test_"):
        return "test/" + field_name[5:].replace("_", "/", 1)
    if field_name.startswith("train_"):
        return "train/" + field_name[6:]
    return "cost/" + field_name


@dataclass
class Orchestrator:
    fabric: object
    config: ExperimentConfig
    scenes: Scenes
    split: FederatedSplit
    clients: list[Client] = field(init=False)

    def __post_init__(self) -> None:
        cfg, fabric = self.config, self.fabric
        self.device = fabric.device
        self.rank, self.world = fabric.global_rank, fabric.world_size
        self.strategy = STRATEGIES[cfg.federated.strategy](cfg.federated)
        torch.manual_seed(cfg.seed)  # the same initial model in every process
        initial = build_scholar(cfg).to(self.device)
        self.keys = shared_keys(initial, cfg.federated.scope, self.strategy)
        if isinstance(self.strategy, FedOpt):
            self.strategy.trainable = parameter_keys(initial) & set(self.keys)
        state = initial.state_dict()
        self.global_weights = {k: state[k].detach().clone() for k in self.keys}
        float_keys = {k for k, v in state.items() if torch.is_floating_point(v)}
        # With nothing kept locally every client holds the same model after aggregation:
        # one evaluation per process gives every client's (identical) figures.
        self.identical_models = float_keys == set(self.keys)
        self.channels_last = cfg.model.channels_last and self.scenes.images is not None
        augment = Augment() if cfg.data.augment and self.scenes.images is not None else None
        copies = cfg.data.augment_copies if augment is not None else 1
        self.clients = []
        for shard in self.split.clients:
            if shard.client % self.world != self.rank:
                continue
            model = build_scholar(cfg).to(self.device)
            model.load_state_dict(initial.state_dict())
            batches = SceneBatches(
                self.scenes.inputs,
                self.scenes.targets,
                shard.train,
                cfg.train.batch_size,
                copies=copies,
                augment=augment,
                seed=client_seed(cfg.seed, shard.client),
                device=self.device,
            )
            self.clients.append(
                Client(
                    shard.client,
                    shard.train,
                    model,
                    model.configure_optimizers(),
                    batches,
                    self.strategy.client_plugins(shard.client),
                )
            )
        test = self.split.test
        inputs = self.scenes.inputs[torch.as_tensor(test)]
        if self.scenes.images is not None:
            inputs = normalize(inputs)
            if self.channels_last:
                inputs = inputs.contiguous(memory_format=torch.channels_last)
        self.test_inputs = inputs.to(self.device)
        self.test_targets = self.scenes.targets[torch.as_tensor(test)]
        self.initial_bytes = nbytes(self.global_weights)
        self._warm_up(initial)

    def _warm_up(self, model: torch.nn.Module) -> None:
        """One untimed training step on a throwaway copy, so that kernel selection and
        allocator set-up are not billed to the first client's first round."""
        if not self.clients:
            return
        model = copy.deepcopy(model).train()
        x, y = next(iter(self.clients[0].batches.peek()))
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        with self.fabric.autocast():
            loss = torch.nn.functional.mse_loss(model(x).float(), y)
        loss.backward()

    # ------------------------------------------------------------------ one round

    def train_round(self, round_: int, progress=None) -> dict[int, tuple[LocalStats, Usage, int]]:
        cfg = self.config
        out = {}
        for client in self.clients:
            if cfg.train.reset_optimizer:
                client.optimizer = client.model.configure_optimizers()
            ctx = LocalContext(
                client.index,
                round_,
                client.model,
                self.global_weights,
                self.device,
                self.fabric.autocast,
            )
            on_epoch = None if progress is None else (lambda e, c=client.index: progress(c, e))
            with measure(self.device) as usage:
                stats = train_locally(
                    client,
                    ctx,
                    cfg.train.epochs,
                    cfg.train.max_batches,
                    self.channels_last,
                    self.fabric.autocast,
                    on_epoch,
                )
            out[client.index] = (stats, usage, nbytes(client.upload(self.keys)))
        return out

    def aggregate(self) -> None:
        """Sample-weighted mean over all clients of all processes, then the server update."""
        sums, total = weighted_sum(
            ((c.n_samples, c.upload(self.keys)) for c in self.clients), self.keys
        )
        if self.world > 1:
            # One collective for everything: the flattened sums and the sample count.
            parts = [
                sums.get(k, torch.zeros_like(self.global_weights[k], dtype=torch.float64)).flatten()
                for k in self.keys
            ]
            flat = torch.cat(
                [*parts, torch.tensor([total], dtype=torch.float64, device=self.device)]
            )
            flat = self.fabric.all_reduce(flat, reduce_op="sum")
            total, offset = float(flat[-1]), 0
            for k in self.keys:
                size = self.global_weights[k].numel()
                sums[k] = flat[offset : offset + size].view_as(self.global_weights[k])
                offset += size
        mean = finish_mean(sums, total, like=self.global_weights)
        self.global_weights = self.strategy.server_update(self.global_weights, mean)
        for client in self.clients:
            client.download(self.global_weights)

    def evaluate_clients(self) -> dict[int, RegressionScores]:
        cfg = self.config.train
        scores: dict[int, RegressionScores] = {}
        for client in self.clients:
            if self.identical_models and scores:
                scores[client.index] = next(iter(scores.values()))
                continue
            scores[client.index] = evaluate(
                client.model,
                self.test_inputs,
                self.test_targets,
                cfg.eval_batch_size,
                self.fabric.autocast,
                cfg.compat_batch_metrics,
            )
        return scores

    def gather(self, round_: int, trained, scores, seconds: float) -> RoundLog:
        """Every client's row, from every process (rows of other processes are zero)."""
        table = torch.zeros(len(self.split.clients), len(FIELDS), dtype=torch.float64)
        for client in self.clients:
            stats, usage, up = trained[client.index]
            down = nbytes(self.global_weights) + (self.initial_bytes if round_ == 1 else 0)
            costs = [
                stats.loss,
                stats.samples,
                usage.cpu_s,
                usage.wall_s,
                math.nan if usage.gpu_util is None else usage.gpu_util,
                math.nan if usage.gpu_mem_mb is None else usage.gpu_mem_mb,
                up,
                down,
            ]
            table[client.index] = torch.tensor(
                score_row(scores[client.index]) + costs, dtype=torch.float64
            )
        if self.world > 1:
            table = self.fabric.all_reduce(table.to(self.device), reduce_op="sum").cpu()
        return RoundLog(round_, table.numpy(), seconds)

    def run_round(self, round_: int, progress=None) -> RoundLog:
        start = time.perf_counter()
        trained = self.train_round(round_, progress)
        self.aggregate()
        scores = self.evaluate_clients()
        return self.gather(round_, trained, scores, time.perf_counter() - start)


def torch_threads(config: ExperimentConfig, local_world_size: int) -> int:
    """Threads per process: the setting, else this machine's cores over its processes."""
    if config.runtime.threads is not None:
        return config.runtime.threads
    cores = (
        len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    )
    return max(1, cores // local_world_size)
