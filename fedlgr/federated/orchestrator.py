"""The Fabric-based federated round orchestrator (SPEC 4.3).

``setup`` -> ``fabric.launch(main)`` -> an explicit round loop. In each round every client
trains its local model for E epochs on its shard of the current task, uploads the tensors
its strategy and scope share, the server aggregates (sample-weighted mean, then the
strategy's server update), every client downloads the new global tensors, at a task's last
round ends the task (importance, memories, generators: plugins' ``on_task_end``), and
evaluates its own model on the shared test set - the scenes of every task seen so far, and
each task's scenes on their own. All client and server state lives in memory (see
``Client.state_dict``).

Plain FL is a schedule of one task, "all", of ``federated.rounds`` rounds. By default all
clients run in one process on one device. With ``runtime.devices=N`` (and
``runtime.num_nodes``) the clients are dealt round-robin to the processes, each process
trains its own, and aggregation is one weighted ``all_reduce``; per-client rows are
reduced to rank 0, which alone logs. Seeds are per client, so both modes compute the same
numbers.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from fedlgr.config import ExperimentConfig
from fedlgr.continual import continual_plugins
from fedlgr.continual.schedule import ALL
from fedlgr.data.augment import Augment, SceneBatches, normalize
from fedlgr.data.columns import LABEL_SHORT_NAMES
from fedlgr.data.dataset import Scenes
from fedlgr.data.splits import FederatedSplit
from fedlgr.federated.aggregate import finish_mean, weighted_sum
from fedlgr.federated.client import Client, LocalStats, train_locally
from fedlgr.federated.evaluation import predict
from fedlgr.federated.plugins import LocalContext
from fedlgr.federated.scope import nbytes, parameter_keys, shared_keys
from fedlgr.federated.strategies import STRATEGIES, FedOpt
from fedlgr.models.scholar import build_scholar
from fedlgr.runtime import available_cores
from fedlgr.tracking.metrics import regression_scores
from fedlgr.tracking.resources import Usage, measure


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
    Field("bytes_up", "cost/bytes_up"),
    Field("bytes_down", "cost/bytes_down"),
]


def plugin_fields(plugins) -> list[Field]:
    """What the plugins measure at task ends: ``<plugin>_<name>``, MLflow ``<plugin>/<name>``."""
    return [Field(f"{p.name}_{m}", f"{p.name}/{m}") for p in plugins for m in p.metric_names]


def make_fields(tasks: list[str]) -> list[Field]:
    """``test_*``: all seen tasks' test scenes (the whole test set in FL), per action too;
    ``task_<name>_*``: each task's test scenes (FCL only); then the costs."""
    fields = _score_fields("test", "test", per_action=True)
    if tasks != [ALL]:
        for task in tasks:
            fields += _score_fields(f"task_{task}", f"task/{task}", per_action=False)
    return fields + COST_FIELDS


def client_seed(seed: int, client: int) -> int:
    return int(np.random.SeedSequence([seed, client]).generate_state(1)[0])


@dataclass
class RoundLog:
    """Per-client rows of one round (after the collective: all clients)."""

    round: int
    task: str
    fields: list[Field]
    table: np.ndarray  # (clients, len(fields))
    seconds: float

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
        """MLflow metrics of this round: means over clients and per-client values."""
        out: dict[str, float] = {"round/seconds": self.seconds}
        for f, column in zip(self.fields, self.table.T, strict=True):
            if not np.isnan(column).all():
                out[f.key] = float(np.nanmean(column))
            for client, value in enumerate(column):
                if not math.isnan(value):
                    out[f"client{client}/{f.key}"] = float(value)
        return out


def _combine(a: Usage, b: Usage) -> Usage:
    """The cost of two consecutive pieces of a client's work."""
    gpu = None
    if a.gpu_util is not None and b.gpu_util is not None:
        gpu = (a.gpu_util * a.wall_s + b.gpu_util * b.wall_s) / max(a.wall_s + b.wall_s, 1e-9)
    mem = max((m for m in (a.gpu_mem_mb, b.gpu_mem_mb) if m is not None), default=None)
    return Usage(a.cpu_s + b.cpu_s, a.wall_s + b.wall_s, gpu, mem)


class Orchestrator:
    def __init__(self, fabric, config: ExperimentConfig, scenes: Scenes, split: FederatedSplit):
        self.fabric, self.config, self.scenes, self.split = fabric, config, scenes, split
        cfg = config
        self.device = fabric.device
        self.rank, self.world = fabric.global_rank, fabric.world_size
        self.tasks = list(cfg.continual.tasks) or [ALL]
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
        self.channels_last = cfg.model.channels_last and scenes.images is not None
        augment = Augment() if cfg.data.augment and scenes.images is not None else None
        copies = cfg.data.augment_copies if augment is not None else 1
        self.clients: list[Client] = []
        for shard in split.clients:
            if shard.client % self.world != self.rank:
                continue
            model = build_scholar(cfg).to(self.device)
            model.load_state_dict(initial.state_dict())
            seed = client_seed(cfg.seed, shard.client)
            data = {
                task: SceneBatches(
                    scenes.inputs,
                    scenes.targets,
                    shard.train if task == ALL else shard.tasks[task],
                    cfg.train.batch_size,
                    copies=copies,
                    augment=augment,
                    seed=seed + t,
                    device=self.device,
                )
                for t, task in enumerate(self.tasks)
            }
            plugins = [
                *self.strategy.client_plugins(shard.client),
                *continual_plugins(cfg.continual, shard.client, cfg.seed),
            ]
            self.clients.append(
                Client(shard.client, model, model.configure_optimizers(), data, plugins)
            )
        # Every client of every process has the same kinds of plugin (and every process has
        # a client: the config refuses more processes than clients): the first says which.
        self.plugin_fields = plugin_fields(self.clients[0].plugins)
        self.fields = make_fields(self.tasks) + self.plugin_fields
        self._prepare_test_set()
        self.initial_bytes = nbytes(self.global_weights)
        self._warm_up(initial)

    def _prepare_test_set(self) -> None:
        test = self.split.test
        inputs = self.scenes.inputs[torch.as_tensor(test)]
        if self.scenes.images is not None:
            inputs = normalize(inputs)
            if self.channels_last:
                inputs = inputs.contiguous(memory_format=torch.channels_last)
        self.test_inputs = inputs.to(self.device)
        self.test_targets = self.scenes.targets[torch.as_tensor(test)]
        # Rows of the test set per task, and of every task seen up to each point.
        where = {t: np.searchsorted(test, self.split.test_tasks[t]) for t in self.tasks if t != ALL}
        self.test_rows = {t: torch.as_tensor(r) for t, r in where.items()}
        self.seen_rows = [
            torch.as_tensor(np.sort(np.concatenate([where[t] for t in self.tasks[: k + 1]])))
            if self.tasks != [ALL]
            else torch.arange(len(test))
            for k in range(len(self.tasks))
        ]

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

    def context(self, client: Client, round_: int, task: int) -> LocalContext:
        return LocalContext(
            client.index,
            round_,
            client.model,
            self.global_weights,
            self.device,
            self.fabric.autocast,
            task,
            self.config.train.epochs,
            self.config.train.max_batches,
            self.tasks[task],
            client.batches,
            client.optimizer,
            seen=[client.data[t] for t in self.tasks[: task + 1]],
        )

    def train_round(
        self, round_: int, task: int = 0, first_of_task: bool = False, progress=None
    ) -> dict[int, tuple[LocalStats, Usage, int]]:
        cfg = self.config
        out = {}
        for client in self.clients:
            client.task = self.tasks[task]
            if cfg.train.reset_optimizer:
                client.optimizer = client.model.configure_optimizers()
            ctx = self.context(client, round_, task)
            on_epoch = None if progress is None else (lambda e, c=client.index: progress(c, e))
            with measure(self.device) as usage:
                if first_of_task:
                    for plugin in client.plugins:
                        plugin.on_task_start(ctx)
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

    def end_task(self, round_: int, task: int) -> dict[int, tuple[Usage, dict[str, float]]]:
        """Each client's end of task (plugins' ``on_task_end``), measured as its work, and
        what its plugins measured then (``<plugin>_<name>``)."""
        out = {}
        for client in self.clients:
            ctx = self.context(client, round_, task)
            with measure(self.device) as usage:
                for plugin in client.plugins:
                    plugin.on_task_end(ctx)
            figures = {  # outside the measurement: diagnostics are not the client's work
                f"{p.name}_{k}": v for p in client.plugins for k, v in p.task_metrics(ctx).items()
            }
            out[client.index] = (usage, figures)
        return out

    def evaluate_clients(self, task: int) -> dict[int, list[float]]:
        """Each client's score fields: all tasks seen so far, then each task on its own."""
        cfg = self.config.train
        out: dict[int, list[float]] = {}
        for client in self.clients:
            if self.identical_models and out:
                out[client.index] = next(iter(out.values()))
                continue
            pred = predict(
                client.model, self.test_inputs, cfg.eval_batch_size, self.fabric.autocast
            )
            seen = self.seen_rows[task]
            s = regression_scores(pred[seen], self.test_targets[seen], cfg.compat_batch_metrics)
            values = [
                s.loss,
                s.mean_rmse,
                s.mean_pcc,
                *s.mse.tolist(),
                *s.rmse.tolist(),
                *s.pcc.tolist(),
            ]
            for rows in self.test_rows.values():
                t = regression_scores(pred[rows], self.test_targets[rows], cfg.compat_batch_metrics)
                values += [t.loss, t.mean_rmse, t.mean_pcc]
            out[client.index] = values
        return out

    def gather(self, round_: int, task: int, trained, ended, scores, seconds: float) -> RoundLog:
        """Every client's row, from every process (rows of other processes are zero)."""
        table = torch.zeros(len(self.split.clients), len(self.fields), dtype=torch.float64)
        for client in self.clients:
            stats, usage, up = trained[client.index]
            figures: dict[str, float] = {}
            if client.index in ended:
                usage = _combine(usage, ended[client.index][0])
                figures = ended[client.index][1]
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
            measured = [figures.get(f.name, math.nan) for f in self.plugin_fields]
            table[client.index] = torch.tensor(
                scores[client.index] + costs + measured, dtype=torch.float64
            )
        if self.world > 1:
            table = self.fabric.all_reduce(table.to(self.device), reduce_op="sum").cpu()
        return RoundLog(round_, self.tasks[task], self.fields, table.numpy(), seconds)

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict:
        """This process's part of the run's state: the server's (global tensors, strategy
        state; the same in every process) and its own clients'."""
        return {
            "server": {"global": self.global_weights, "strategy": self.strategy.state_dict()},
            "clients": {c.index: c.state_dict() for c in self.clients},
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore a checkpoint's server state and this process's clients (``state`` holds
        every client of every process)."""
        server = state["server"]
        self.global_weights = {k: v.to(self.device) for k, v in server["global"].items()}
        self.strategy.load_state_dict(to_device(server["strategy"], self.device))
        for client in self.clients:
            client.load_state_dict(to_device(state["clients"][client.index], self.device))

    def run_round(
        self,
        round_: int,
        task: int = 0,
        first_of_task: bool = False,
        last_of_task: bool = False,
        progress=None,
    ) -> RoundLog:
        start = time.perf_counter()
        trained = self.train_round(round_, task, first_of_task, progress)
        self.aggregate()
        ended = self.end_task(round_, task) if last_of_task else {}
        scores = self.evaluate_clients(task)
        return self.gather(round_, task, trained, ended, scores, time.perf_counter() - start)


def to_device(value, device: torch.device):
    """``value`` with every tensor moved to ``device`` (dicts, lists, tuples walked)."""
    if isinstance(value, torch.Tensor):
        # Generator states are CPU byte tensors whatever the device; keep them there.
        return value if value.dtype == torch.uint8 else value.to(device)
    if isinstance(value, dict):
        return {k: to_device(v, device) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(to_device(v, device) for v in value)
    return value


def torch_threads(config: ExperimentConfig, local_world_size: int) -> int:
    """Threads per process: the setting, else this machine's cores over its processes."""
    if config.runtime.threads is not None:
        return config.runtime.threads
    return max(1, available_cores() // local_world_size)
