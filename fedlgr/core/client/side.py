"""The client side of a federation: everything that runs where the clients are.

:class:`ClientSide` holds some clients - all of them in one process, a process's share
under Fabric, one in the Flower runtime - each with its data shard, model, optimiser and
plugins (the strategy's client part, the CL method: importance, memories, FedLGR's
generator and labeller). It answers the server's :mod:`messages`: ``train`` (take the
global tensors if sent, train locally, upload the shared tensors; only the clients the
strategy chose) and ``evaluate`` (every client: take the new global tensors, end the task
at its last round, score on the test scenes). The top and every plugin's state stay here;
what leaves is checked against the shared keys.
"""

from __future__ import annotations

import contextlib
import copy
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from fedlgr.core.client.idle import (
    IdleStates,
    compact,
    complete,
    give_back_freed_memory,
    idle_keeping,
    remove_stale,
    spill_prefix,
)
from fedlgr.core.client.plugins import ClientPlugin, LocalContext
from fedlgr.core.client.pool import ClientPool, Resolved
from fedlgr.core.client.stacked import refuse_plugins, train_batched
from fedlgr.core.client.training import Client, train_locally
from fedlgr.core.continual import continual_plugins
from fedlgr.core.data.augment import SceneBatches, augmenter
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
from fedlgr.core.state import to_device
from fedlgr.core.strategies import build_strategy
from fedlgr.errors import FedlgrError

if TYPE_CHECKING:
    from fedlgr.core.data.scenes import FederatedSplit, Scenes
    from fedlgr.core.settings import ExperimentConfig


CPU = torch.device("cpu")
SPARE_MODELS = 32  # rested clients' models kept to wake others with, at most


def _poisoned(targets: torch.Tensor, label: float) -> torch.Tensor:
    """Every scene rated ``label`` for every action (``federated.faults.attack=labels``)."""
    return torch.full_like(targets, label)


def _spill_folder(parent: Path | None, keeping: str) -> tempfile.TemporaryDirectory:
    """A new folder for idle clients' states under ``parent`` (None: the system's temporary
    folder), after removing those killed processes left there; a folder that cannot be
    made is one line naming it."""
    try:
        if parent is not None:
            parent.mkdir(parents=True, exist_ok=True)
            remove_stale(parent)
        return tempfile.TemporaryDirectory(prefix=spill_prefix(), dir=parent)
    except OSError as err:
        where = parent or Path(tempfile.gettempdir())
        raise FedlgrError(
            f"runtime.idle_clients={keeping}: cannot make a folder for idle clients' states "
            f"in {where} ({err.strerror or err}); {_elsewhere(parent)}"
        ) from None


def _elsewhere(parent: Path | None) -> str:
    """How to keep idle clients' states out of ``parent`` (None: the temporary folder)."""
    moved_by = "the TMPDIR variable" if parent is None else "tracking.checkpoint_dir"
    return f"choose another with {moved_by}, or keep them in memory (runtime.idle_clients=memory)"


def _measures_rounds(plugin: ClientPlugin) -> bool:
    """Does ``plugin`` measure something every round (``round_metrics``)?"""
    return type(plugin).round_metrics is not ClientPlugin.round_metrics


def client_seed(seed: int, client: int) -> int:
    return int(np.random.SeedSequence([seed, client]).generate_state(1)[0])


class ClientSide:
    """``spill``: where the folder of idle clients' states is made, for those beyond
    ``runtime.idle_memory_mb`` (:mod:`fedlgr.core.client.idle`; None: the system's
    temporary folder). ``resolved``: how the clients train, as the launch decided it
    (None: decided here, for this process's torch threads)."""

    def __init__(
        self,
        config: ExperimentConfig,
        scenes: Scenes,
        split: FederatedSplit,
        indices: list[int],
        device: torch.device,
        autocast=contextlib.nullcontext,
        spill: Path | None = None,
        resolved: Resolved | None = None,
    ):
        # How this process's clients train: decided by the launch, else here
        rt, threads = config.runtime, torch.get_num_threads()
        self.resolved = resolved or Resolved.decide(
            rt.concurrency, rt.workers, rt.threads, device, len(indices)
        )
        cfg = config
        self.config, self.scenes, self.split = config, scenes, split
        self.pool = ClientPool(self.resolved.workers, threads, device)
        self.device, self.autocast = device, autocast
        self.tasks = list(cfg.continual.tasks) or [ALL]
        self.strategy = build_strategy(cfg.federated)  # its client part
        self.initial = initial = initial_scholar(cfg).to(device)
        self.keys = shared_keys(initial, cfg.federated.scope, self.strategy)
        self._model_kinds(initial)
        self.channels_last = cfg.model.channels_last and scenes.images is not None
        self.augment = augmenter(cfg.data, images=scenes.images is not None)
        self.copies = cfg.data.augment_copies if self.augment is not None else 1
        faults = cfg.federated.faults  # attack=labels: these clients train on poisoned labels
        self.poisoned = Faults(faults, cfg.data.clients, cfg.seed).poisoned
        self.shards = {s.client: s for s in split.clients if s.client in indices}
        self._global: torch.nn.Module | None = None  # see global_model
        self.spare: list[torch.nn.Module] = []  # rested clients' models, to wake others with
        self._check_batched()
        # does a plugin measure something every round (every client has the same kinds)?
        self.measures_rounds = any(_measures_rounds(p) for p in self._plugins(0))
        # The global tensors the clients hold (the initial ones until the first download)
        state = initial.state_dict()
        self.shared: Weights = {k: state[k] for k in self.keys}
        self.keeping = idle_keeping(cfg.runtime, len(self.shards))
        budget = {"memory": None, "disk": 0}.get(self.keeping, cfg.runtime.idle_memory_mb * 2**20)
        self._spill = None  # the folder idle clients' states spill to, removed by close()
        if self.keeping != "live":
            self._spill = _spill_folder(spill, self.keeping)
        folder = self._spill and Path(self._spill.name)
        self.idle = IdleStates(budget, folder, _elsewhere(spill))
        self.awake: dict[int, Client] = {}
        if self.keeping == "live":  # else a client is built when it is first woken
            for index in self.shards:
                self.wake(index)
        self._prepare_test_set()
        self._warm_up(initial)

    def _model_kinds(self, initial: torch.nn.Module) -> None:
        float_keys = {k for k, v in initial.state_dict().items() if torch.is_floating_point(v)}
        # With nothing kept locally every client holds the same model after aggregation:
        # one evaluation gives every client's (identical) figures.
        self.identical_models = float_keys == set(self.keys)
        # The root's floating-point tensors, where every one of them is shared (FedRoot
        # with any strategy that shares the whole root): see ``predictions``.
        root_keys = {k for k in float_keys if k.startswith("root.")}
        self.root_keys = sorted(root_keys) if root_keys <= set(self.keys) else []

    def _check_batched(self) -> None:
        """``runtime.concurrency=batched``: refused before any run is started (not at round
        1) where a client has plugins or scales its losses."""
        if self.resolved.concurrency != "batched" or not self.shards:
            return
        refuse_plugins([self.build(next(iter(self.shards)))])
        if self._scaler() is not None:
            raise FedlgrError(
                "runtime.concurrency=batched does not scale losses yet: with "
                "train.precision=16-mixed on a GPU use runtime.concurrency=threads or "
                "sequential, or train.precision=bf16-mixed"
            )

    def build(self, index: int) -> Client:
        """Client ``index`` as it starts the run: the initial model, a fresh optimiser, its
        plugins, its batches of each task (their generators seeded per client)."""
        cfg, shard = self.config, self.shards[index]
        seed = client_seed(cfg.seed, index)
        targets = self.scenes.targets
        if index in self.poisoned:
            targets = _poisoned(targets, cfg.federated.faults.label)
        data = {
            task: SceneBatches(
                self.scenes.inputs,
                targets,
                shard.train if task == ALL else shard.tasks[task],
                cfg.train.batch_size,
                copies=self.copies,
                augment=self.augment,
                seed=seed + t,
                device=self.device,
            )
            for t, task in enumerate(self.tasks)
        }
        plugins = self._plugins(index)
        model = self._initial_model()
        optimizer = model.configure_optimizers()
        return Client(index, model, optimizer, data, plugins, scaler=self._scaler())

    def _initial_model(self) -> torch.nn.Module:
        """A copy of the initial model: a rested client's model given the initial state,
        flags and no gradients (as a new copy has them), else a new copy."""
        if not self.spare:
            return copy.deepcopy(self.initial)
        model = self.spare.pop()
        model.load_state_dict(self.initial.state_dict())
        for p, q in zip(model.parameters(), self.initial.parameters(), strict=True):
            p.grad = None
            p.requires_grad_(q.requires_grad)
        for m, n in zip(model.modules(), self.initial.modules(), strict=True):
            m.training = n.training
        return model

    # ------------------------------------------------------------------ idle clients

    @property
    def clients(self) -> list[Client]:
        """This side's clients, whole (``runtime.idle_clients=live``; elsewhere those
        awake now)."""
        return [self.awake[i] for i in sorted(self.awake)]

    def wake(self, index: int) -> Client:
        """Client ``index``, whole: as it is if awake, else built again and given its kept
        state and the global tensors it holds. Building draws nothing from the
        process's random generators (a generator's layers are made by its plugin)."""
        if index in self.awake:
            return self.awake[index]
        with torch.random.fork_rng(devices=[]):
            client = self.build(index)
            if index in self.idle:
                client.load_state_dict(
                    to_device(complete(self.idle.take(index), self.shared), self.device)
                )
            else:  # never woken yet: as it started the run, holding the global tensors
                client.download(self.shared)
        self.awake[index] = client
        return client

    def rest(self, client: Client) -> None:
        """``client`` goes idle: whole with ``runtime.idle_clients=live``, else as its
        compact state (:mod:`.idle`) and its model, optimiser and plugins let go."""
        if self.keeping == "live":
            return
        state = to_device(compact(client.state_dict(), self.shared), CPU)
        reuse = len(self.spare) < SPARE_MODELS
        if reuse:  # the kept tensors must not be the model's own, which another will use
            state["model"] = {k: v.clone() for k, v in state["model"].items()}
        self.idle.put(client.index, state, set(self.keys))
        del self.awake[client.index]
        if reuse:
            self.spare.append(client.model)

    def rest_all(self, clients: list[Client] | None = None) -> None:
        """Put ``clients`` (every awake one by default) to rest, then hand the memory they
        freed back to the system (:func:`.idle.give_back_freed_memory`)."""
        if self.keeping == "live":
            return
        for client in self.clients if clients is None else clients:
            self.rest(client)
        give_back_freed_memory()

    def n_samples(self, index: int, task: int) -> int:
        """Client ``index``'s training scenes in ``task`` (its aggregation weight)."""
        shard, name = self.shards[index], self.tasks[task]
        return len(shard.train if name == ALL else shard.tasks[name])

    def close(self) -> None:
        """Remove the idle clients' folder and files."""
        self.idle.clear()
        if self._spill is not None:
            self._spill.cleanup()

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
        if not self.shards:
            return
        client = self.clients[0] if self.clients else self.build(next(iter(self.shards)))
        x, y = next(iter(client.batches.peek()))
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
            ins = dict.fromkeys(self.shards, ins)
        chosen = [self.wake(i) for i in sorted(ins) if i in self.shards]  # awake to evaluate
        for client in chosen:
            message = ins[client.index]
            if message.weights is not None:
                client.download(message.weights)
            client.task = self.tasks[message.plan.task]
            if cfg.train.reset_optimizer:
                client.optimizer = client.model.configure_optimizers()
        if self.resolved.concurrency == "batched":
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
        """Every client takes the new global tensors; at a task's last round every client
        ends the task (measured as its work); the clients ``ins`` names (all by default)
        score their models. The others send nothing back. Idle clients go back to rest."""
        plan = ins.plan
        prefix = SCOPE_PREFIX[self.config.federated.scope]
        check_shared(ins.weights, self.keys, "the server's download", prefix)
        for client in self.clients:
            client.download(ins.weights)
        self.shared = ins.weights
        self.idle.download(set(self.keys))
        scored = sorted(self.shards if ins.clients is None else set(ins.clients) & set(self.shards))
        ended = self._finish_rounds(plan, scored)
        predictions = self.predictions(ins.weights, scored)
        out = []
        for index in sorted(set(scored) | set(ended)):
            usage, figures = ended.get(index, (None, {}))
            if index in predictions:
                figures = self.scores(predictions[index], plan.task) | figures
            out.append(EvaluateRes(index, figures | ({} if usage is None else usage.figures())))
        self.rest_all()
        return out

    def _finish_rounds(self, plan, scored: list[int]) -> dict[int, tuple[Usage | None, Figures]]:
        """:meth:`finish_round` of every client at a task's last round, else of the scored
        ones where a plugin measures something each round: a few at a time where idle
        clients rest compact, each put back to rest after."""
        if plan.last_of_task:
            ending = list(self.shards)
        elif self.measures_rounds:
            ending = scored
        else:
            return {}
        finish = lambda c: self.finish_round(c, plan)  # noqa: E731
        done = self._in_turns(ending, lambda clients: self._side_by_side(finish, clients))
        return dict(zip(ending, done, strict=True))

    def _plugins(self, index: int) -> list[ClientPlugin]:
        """Client ``index``'s plugins as they start the run: the strategy's, the CL method's."""
        cfg = self.config
        return [
            *self.strategy.client_plugins(index),
            *continual_plugins(cfg.continual, index, cfg.seed),
        ]

    def _in_turns(self, indices: list[int], work) -> list:
        """``work(clients)`` over ``indices``' clients, woken: all at once where idle
        clients stay whole, else a pool's width at a time, each turn put back to rest
        after its work (so a fleet is never whole at once); the results in order."""
        width = len(indices) if self.keeping == "live" else self.pool.workers
        out = []
        for at in range(0, len(indices), max(width, 1)):
            clients = [self.wake(i) for i in indices[at : at + width]]
            out += work(clients)
            self.rest_all(clients)
        return out

    def predictions(self, received: Weights, scored: list[int]) -> dict[int, torch.Tensor]:
        """The ``scored`` clients' outputs on the test scenes. Clients that hold the same
        model share one pass (nothing kept locally); clients that hold the same root
        (FedRoot, the root as received) share the root's pass over the test set and add
        their own top's: one root pass plus N tops instead of N whole models, and an idle
        client lends only its top."""
        cfg, autocast, map_ = self.config.train, self.autocast, self.pool.map
        if not scored:
            return {}
        if self.identical_models:
            model = self.global_model(received)
            pred = predict(model, self.test_inputs, cfg.eval_batch_size, autocast, map_)
            return dict.fromkeys(scored, pred)
        tops = self._tops_on_the_global_root(scored) if self.root_keys and len(scored) > 1 else None
        if tops is not None:
            root = self.global_model(received).root
            preds = predict_tops(root, tops, self.test_inputs, cfg.eval_batch_size, autocast, map_)
            return dict(zip(scored, preds, strict=True))
        preds = self._in_turns(
            scored,
            lambda clients: self.pool.map(
                lambda c: predict(c.model, self.test_inputs, cfg.eval_batch_size, autocast),
                clients,
            ),
        )
        return dict(zip(scored, preds, strict=True))

    def global_model(self, received: Weights) -> torch.nn.Module:
        """A model holding the global tensors ``received`` (outputs need nothing else where
        every floating-point tensor is shared, or of the root alone): with whole clients
        the first one's, as it downloaded them; else one kept for this."""
        if self.keeping == "live" and self.clients:
            return self.clients[0].model
        if self._global is None:
            self._global = copy.deepcopy(self.initial)
        state = self._global.state_dict()
        with torch.no_grad():
            for key, value in received.items():
                state[key].copy_(value)
        return self._global

    def holds_root(self, index: int) -> bool:
        """Is the client's root exactly the global one (no task end changed it)?"""
        return self.top(index) is not None

    def top(self, index: int) -> torch.nn.Module | None:
        """Client ``index``'s top where its root is the global one (no task end changed it),
        else None: its own module if awake, else one given its kept top (a kept state is
        read once: from its file, if it spilled)."""
        if index in self.awake:
            model = self.awake[index].model
            state = model.state_dict()
            held = all(torch.equal(state[k], self.shared[k]) for k in self.root_keys)
            return model.top if held else None
        kept = self.idle.get(index)
        if kept is not None and any(k in kept["model"] for k in self.root_keys):
            return None
        top = copy.deepcopy(self.initial.top)
        if kept is not None:  # else never woken: the initial top
            model = complete(kept, self.shared)["model"]
            top.load_state_dict({k[4:]: v for k, v in model.items() if k.startswith("top.")})
        return top

    def _tops_on_the_global_root(self, scored: list[int]) -> list[torch.nn.Module] | None:
        """The ``scored`` clients' tops, if every one holds the global root; else None."""
        tops = []
        for index in scored:
            top = self.top(index)
            if top is None:
                return None
            tops.append(top)
        return tops

    def finish_round(self, client: Client, plan) -> tuple[Usage | None, Figures]:
        """The plugins' round figures on the received model, then, at a task's last
        round, the task end (its usage, and its costs and figures)."""
        figures = {}
        if any(_measures_rounds(p) for p in client.plugins):
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
        compat = self.config.train.compat_batch_metrics
        seen, task_rows = self.test.rows(task, compat)
        s = regression_scores(pred[seen], self.test_targets[seen], compat)
        out = s.figures("test", per_action=True)
        for name, rows in task_rows.items():
            t = regression_scores(pred[rows], self.test_targets[rows], compat)
            out |= t.figures(f"task/{name}")
        return out

    # ------------------------------------------------------------------ private state

    def state_dict(self) -> dict[int, dict]:
        """Every client's private state (model, optimiser, plugins, generators); an idle
        client's as it is kept: compact, without the global tensors (the server's state
        holds them)."""
        states = {c.index: c.state_dict() for c in self.clients}
        # a client never woken yet has none: it starts as every client starts the run
        return states | {i: self.idle.get(i) for i in self.shards if i in self.idle}

    def load_state_dict(self, states: dict[int, dict], shared: Weights | None = None) -> None:
        """Restore :meth:`state_dict`'s states of this side's clients; ``shared``: the
        global tensors the clients hold, for states kept compact (None: they are whole)."""
        if shared is not None:
            self.shared = {k: shared[k].to(self.device) for k in self.keys}
        for index in self.shards:
            if index not in states:  # never woken (see state_dict)
                continue
            state = states[index] if shared is None else complete(states[index], self.shared)
            if index in self.awake:
                self.awake[index].load_state_dict(to_device(state, self.device))
                continue
            if index in self.idle:
                self.idle.take(index)
            state = compact(to_device(state, CPU), to_device(self.shared, CPU))
            self.idle.put(index, state, set(self.keys))
