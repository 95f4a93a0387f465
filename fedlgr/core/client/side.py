"""The client side of a federation: everything that runs on a robot.

:class:`ClientSide` holds some clients - all of them in one process, a process's share
under Fabric, one robot's on Flower - each with its data shard, model, optimiser and
plugins (the strategy's client part, the CL method: importance, memories, FedLGR's
generator and labeller). It answers the server's :mod:`messages`: ``train`` (take the
global tensors if sent, train locally, upload the shared tensors; only the clients the
strategy chose) and ``evaluate`` (every client: take the new global tensors, end the task
at its last round, score on the test scenes). The
top and every plugin's state stay here; what leaves is checked against the shared keys.
"""

from __future__ import annotations

import contextlib
import copy
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from fedlgr.core.client.plugins import ClientPlugin, LocalContext
from fedlgr.core.client.pool import ClientPool, resolve
from fedlgr.core.client.stacked import refuse_plugins, train_batched
from fedlgr.core.client.training import Client, train_locally
from fedlgr.core.continual import continual_plugins
from fedlgr.core.data.augment import Augment, SceneBatches
from fedlgr.core.evaluation import eval_set, predict, predict_tops
from fedlgr.core.faults import Faults
from fedlgr.core.messages import (
    EvaluateIns,
    EvaluateRes,
    TrainIns,
    TrainRes,
    Weights,
    check_shared,
)
from fedlgr.core.meters.costs import Usage, measure, process_cpu_seconds, share_process_cpu
from fedlgr.core.meters.scores import regression_scores
from fedlgr.core.metrics import Figures, shared_out
from fedlgr.core.schedule import ALL
from fedlgr.core.scope import SCOPE_PREFIX, initial_scholar, shared_keys
from fedlgr.core.strategies import build_strategy
from fedlgr.errors import FedlgrError

if TYPE_CHECKING:
    from fedlgr.shell.config import ExperimentConfig
    from fedlgr.shell.data.dataset import Scenes
    from fedlgr.shell.data.splits import FederatedSplit


def _poisoned(targets: torch.Tensor, label: float) -> torch.Tensor:
    """Every scene rated ``label`` for every action (``federated.faults.attack=labels``)."""
    return torch.full_like(targets, label)


def client_seed(seed: int, client: int) -> int:
    return int(np.random.SeedSequence([seed, client]).generate_state(1)[0])


class ClientSide:
    def __init__(
        self,
        config: ExperimentConfig,
        scenes: Scenes,
        split: FederatedSplit,
        indices: list[int],
        device: torch.device,
        autocast=contextlib.nullcontext,
    ):
        # How this process's clients train, made explicit (runtime.concurrency, workers)
        cfg = config = resolve(config, device, len(indices))
        self.config, self.scenes, self.split = config, scenes, split
        self.pool = ClientPool(cfg.runtime.workers, torch.get_num_threads(), device)
        self.device, self.autocast = device, autocast
        self.tasks = list(cfg.continual.tasks) or [ALL]
        strategy = build_strategy(cfg.federated)  # its client part
        initial = initial_scholar(cfg).to(device)
        self.keys = shared_keys(initial, cfg.federated.scope, strategy)
        float_keys = {k for k, v in initial.state_dict().items() if torch.is_floating_point(v)}
        # With nothing kept locally every client holds the same model after aggregation:
        # one evaluation gives every client's (identical) figures.
        self.identical_models = float_keys == set(self.keys)
        # The root's floating-point tensors, where every one of them is shared (FedRoot
        # with any strategy that shares the whole root): see ``predictions``.
        root_keys = {k for k in float_keys if k.startswith("root.")}
        self.root_keys = sorted(root_keys) if root_keys <= set(self.keys) else []
        self.channels_last = cfg.model.channels_last and scenes.images is not None
        augment = Augment() if cfg.data.augment and scenes.images is not None else None
        copies = cfg.data.augment_copies if augment is not None else 1
        faults = cfg.federated.faults  # attack=labels: these clients train on poisoned labels
        poisoned = Faults(faults, cfg.data.clients, cfg.seed).poisoned
        self.clients: list[Client] = []
        for shard in split.clients:
            if shard.client not in indices:
                continue
            model = copy.deepcopy(initial)
            seed = client_seed(cfg.seed, shard.client)
            data = {
                task: SceneBatches(
                    scenes.inputs,
                    _poisoned(scenes.targets, faults.label)
                    if shard.client in poisoned
                    else scenes.targets,
                    shard.train if task == ALL else shard.tasks[task],
                    cfg.train.batch_size,
                    copies=copies,
                    augment=augment,
                    seed=seed + t,
                    device=device,
                )
                for t, task in enumerate(self.tasks)
            }
            plugins = [
                *strategy.client_plugins(shard.client),
                *continual_plugins(cfg.continual, shard.client, cfg.seed),
            ]
            optimizer = model.configure_optimizers()
            self.clients.append(
                Client(shard.client, model, optimizer, data, plugins, scaler=self._scaler())
            )
        if cfg.runtime.concurrency == "batched":
            refuse_plugins(self.clients)  # before any run is started, not at round 1
            if any(c.scaler is not None for c in self.clients):
                raise FedlgrError(
                    "runtime.concurrency=batched does not scale losses yet: with "
                    "train.precision=16-mixed on a GPU use runtime.concurrency=threads or "
                    "sequential, or train.precision=bf16-mixed"
                )
        self._prepare_test_set()
        self._warm_up(initial)

    def _scaler(self) -> torch.amp.GradScaler | None:
        """A client's loss scaler: float16 autocast on a GPU needs one (small gradients
        underflow in float16). On CPU, Lightning Fabric runs ``16-mixed`` as bfloat16
        autocast, which needs none."""
        if self.config.train.precision != "16-mixed" or self.device.type != "cuda":
            return None
        return torch.amp.GradScaler(self.device.type)

    def _prepare_test_set(self) -> None:
        self.test = eval_set(
            self.scenes, self.split, self.tasks, self.device, self.channels_last, self.autocast
        )
        # Rows of the test set per task, and of every task seen up to each point.
        self.test_inputs, self.test_targets = self.test.test_inputs, self.test.test_targets
        self.test_rows, self.seen_rows = self.test.test_rows, self.test.seen_rows

    def _warm_up(self, model: torch.nn.Module) -> None:
        """One untimed training step on a throwaway copy, so that kernel selection and
        allocator set-up are not billed to the first client's first round (in every
        worker of the pool: kernels are chosen per thread count)."""
        if not self.clients:
            return
        x, y = next(iter(self.clients[0].batches.peek()))
        if len(x) < 2:  # a client of one scene (BatchNorm cannot train on a single sample)
            x, y = torch.cat([x, x]), torch.cat([y, y])
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)

        def step() -> None:
            copied = copy.deepcopy(model).train()
            with self.autocast():
                loss = torch.nn.functional.mse_loss(copied(x).float(), y)
            loss.backward()

        self.pool.each_worker(step)

    def context(
        self, client: Client, round_: int, task: int, received: Weights | None = None
    ) -> LocalContext:
        global_weights = {k: v for k, v in client.model.state_dict().items() if k in self.keys}
        return LocalContext(
            client.index,
            round_,
            client.model,
            global_weights,
            self.device,
            self.autocast,
            task,
            self.config.train.epochs,
            self.config.train.max_batches,
            self.tasks[task],
            client.batches,
            client.optimizer,
            seen=[client.data[t] for t in self.tasks[: task + 1]],
            scaler=client.scaler,
            received=received or {},
        )

    def start_task(self, client: Client, ctx: LocalContext) -> None:
        """The plugins' ``on_task_start``, once per task: at the first round of the task
        the client trains in (a strategy may not choose it in every round)."""
        if client.started < ctx.task:
            for plugin in client.plugins:
                plugin.on_task_start(ctx)
            client.started = ctx.task

    # ------------------------------------------------------------------ the messages

    def train(self, ins: TrainIns | dict[int, TrainIns], progress=None) -> list[TrainRes]:
        """The local training of the round's chosen clients (``ins``: client -> its
        message, for those of this side; one message: every client of this side), and
        what they upload."""
        cfg = self.config
        if isinstance(ins, TrainIns):
            ins = {c.index: ins for c in self.clients}
        chosen = [c for c in self.clients if c.index in ins]
        for client in chosen:
            message = ins[client.index]
            if message.weights is not None:
                client.download(message.weights)
            client.task = self.tasks[message.plan.task]
            if cfg.train.reset_optimizer:
                client.optimizer = client.model.configure_optimizers()
        if cfg.runtime.concurrency == "batched":
            return self._train_batched(chosen, ins, progress)
        trained = self._side_by_side(lambda c: self._train_one(c, ins[c.index], progress), chosen)
        for usage, res in trained:
            res.figures.update(usage.figures())
        return [res for _, res in trained]

    def _side_by_side(self, work, clients: list[Client]) -> list[tuple[Usage | None, Any]]:
        """``work(client) -> (usage, result)`` for every one of ``clients``, in the pool
        (``runtime.concurrency``): each usage is measured in its own thread there, then given
        its share of the process's CPU seconds (``share_process_cpu``); the costs are read
        from the usages once this is done."""
        if self.pool.workers == 1 or len(clients) <= 1:
            return [work(c) for c in clients]
        start = process_cpu_seconds()
        out = self.pool.map(work, clients)
        share_process_cpu([u for u, _ in out if u is not None], process_cpu_seconds() - start)
        return out

    def _train_one(self, client: Client, ins: TrainIns, progress) -> tuple[Usage, TrainRes]:
        cfg, plan = self.config, ins.plan
        ctx = self.context(client, plan.round, plan.task, ins.payload)
        on_epoch = None if progress is None else (lambda e, c=client.index: progress(c, e))
        with measure(self.device, per_thread=self.pool.workers > 1) as usage:
            self.start_task(client, ctx)
            stats = train_locally(
                client,
                ctx,
                cfg.train.epochs,
                cfg.train.max_batches,
                self.channels_last,
                self.autocast,
                on_epoch,
                self.pool.stop,
            )
        return usage, self.result(client, ctx, stats.figures)

    def result(self, client: Client, ctx: LocalContext, figures: Figures) -> TrainRes:
        """What ``client`` uploads after training: its shared tensors, its plugins'
        payload, its figures (``usage``'s costs are added once they are final)."""
        payload = {k: v for p in client.plugins for k, v in p.payload(ctx).items()}
        return TrainRes(client.index, self.upload(client), client.n_samples, figures, payload)

    def _train_batched(self, chosen: list[Client], ins, progress) -> list[TrainRes]:
        """The chosen clients as one stacked model (``runtime.concurrency=batched``). The
        one measured cost is shared out in proportion to the samples each client trained."""
        cfg = self.config
        ctxs = [
            self.context(c, ins[c.index].plan.round, ins[c.index].plan.task, ins[c.index].payload)
            for c in chosen
        ]
        for client, ctx in zip(chosen, ctxs, strict=True):
            self.start_task(client, ctx)
        on_epoch = None
        if progress is not None:  # one call per epoch of all clients: one per client
            on_epoch = lambda e: [progress(c.index, e) for c in chosen]  # noqa: E731
        with measure(self.device) as usage:
            stats = train_batched(
                chosen,
                ctxs,
                cfg.train.epochs,
                cfg.train.max_batches,
                self.channels_last,
                self.autocast,
                on_epoch,
            )
        total = max(sum(s.samples for s in stats), 1)
        return [
            self.result(c, ctx, s.figures | shared_out(usage.figures(), s.samples / total))
            for c, ctx, s in zip(chosen, ctxs, stats, strict=True)
        ]

    def upload(self, client: Client) -> Weights:
        weights = client.upload(self.keys)
        prefix = SCOPE_PREFIX[self.config.federated.scope]
        check_shared(weights, self.keys, f"client {client.index}'s upload", prefix)
        return weights

    def evaluate(self, ins: EvaluateIns) -> list[EvaluateRes]:
        """Every client takes the new global tensors, ends the task at its last round
        (measured as its work), and scores its model."""
        plan = ins.plan
        prefix = SCOPE_PREFIX[self.config.federated.scope]
        check_shared(ins.weights, self.keys, "the server's download", prefix)
        for client in self.clients:
            client.download(ins.weights)
        ended = self._side_by_side(lambda c: self.finish_round(c, plan), self.clients)
        predictions = self.predictions(ins.weights)
        return [
            EvaluateRes(
                client.index,
                self.scores(pred, plan.task) | figures | ({} if usage is None else usage.figures()),
            )
            for client, pred, (usage, figures) in zip(self.clients, predictions, ended, strict=True)
        ]

    def predictions(self, received: Weights) -> list[torch.Tensor]:
        """Every client's outputs on the test scenes. Clients that hold the same model
        share one pass (nothing kept locally); clients that hold the same root (FedRoot,
        the root as received) share the root's pass over the test set and add their own
        top's: one root pass plus N tops instead of N whole models."""
        cfg, autocast, map_ = self.config.train, self.autocast, self.pool.map
        if self.identical_models:
            model = self.clients[0].model
            pred = predict(model, self.test_inputs, cfg.eval_batch_size, autocast, map_)
            return [pred] * len(self.clients)
        if (
            self.root_keys
            and len(self.clients) > 1
            and all(self.holds_root(c, received) for c in self.clients)
        ):
            tops = [c.model.top for c in self.clients]
            root = self.clients[0].model.root
            return predict_tops(root, tops, self.test_inputs, cfg.eval_batch_size, autocast, map_)
        return self.pool.map(
            lambda c: predict(c.model, self.test_inputs, cfg.eval_batch_size, autocast),
            self.clients,
        )

    def holds_root(self, client: Client, received: Weights) -> bool:
        """Is the client's root exactly the one received (no task end changed it)?"""
        state = client.model.state_dict()
        return all(torch.equal(state[k], received[k]) for k in self.root_keys)

    def finish_round(self, client: Client, plan) -> tuple[Usage | None, Figures]:
        """The plugins' round figures on the received model, then, at a task's last
        round, the task end (its usage, and its costs and figures)."""
        figures = {}
        if any(type(p).round_metrics is not ClientPlugin.round_metrics for p in client.plugins):
            ctx = self.context(client, plan.round, plan.task)
            figures = {  # outside any measurement: diagnostics are not the client's work
                f"{p.name}/{k}": v for p in client.plugins for k, v in p.round_metrics(ctx).items()
            }
        if not plan.last_of_task:
            return None, figures
        usage, ended = self.end_task(client, plan.round, plan.task)
        return usage, figures | ended

    def end_task(self, client: Client, round_: int, task: int) -> tuple[Usage, Figures]:
        """The plugins' ``on_task_end`` (after their ``on_task_start`` if the client trained
        in none of the task's rounds), what it cost, and what they measured then
        (``<plugin>/<name>``)."""
        ctx = self.context(client, round_, task)
        with measure(self.device, per_thread=self.pool.workers > 1) as usage:
            self.start_task(client, ctx)
            for plugin in client.plugins:
                plugin.on_task_end(ctx)
        figures = {  # outside the measurement: diagnostics are not the client's work
            f"{p.name}/{k}": v for p in client.plugins for k, v in p.task_metrics(ctx).items()
        }
        return usage, figures

    def scores(self, pred: torch.Tensor, task: int) -> Figures:
        """The scores of outputs ``pred``: on every task seen so far (per action too),
        then on each task's scenes (FCL)."""
        cfg = self.config.train
        seen = self.seen_rows[task]
        s = regression_scores(pred[seen], self.test_targets[seen], cfg.compat_batch_metrics)
        out = s.figures("test", per_action=True)
        for name, rows in self.test_rows.items():
            t = regression_scores(pred[rows], self.test_targets[rows], cfg.compat_batch_metrics)
            out |= t.figures(f"task/{name}")
        return out

    # ------------------------------------------------------------------ private state

    def state_dict(self) -> dict[int, dict]:
        """Every client's private state (model, optimiser, plugins, generators)."""
        return {c.index: c.state_dict() for c in self.clients}

    def load_state_dict(self, states: dict[int, dict]) -> None:
        for client in self.clients:
            client.load_state_dict(states[client.index])
