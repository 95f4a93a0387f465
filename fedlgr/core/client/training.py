"""A client: its model, optimiser, plugins and data, all in memory, and its local training.

The local loop is deliberately plain - gather a batch, forward, the plugins' hooks,
backward, step - with no per-step host synchronisation beyond what the plugins need, so it
trains as fast as a hand-written PyTorch loop (``bench/train.py`` measures the ratio).
"""

from __future__ import annotations

import contextlib
import copy
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, field

import torch
from torch import nn

from fedlgr.core.client.plugins import ClientPlugin, LocalContext
from fedlgr.core.data.augment import SceneBatches
from fedlgr.core.meters.flops import flop_counter
from fedlgr.core.metrics import Figures
from fedlgr.errors import FedlgrError


@dataclass
class Client:
    index: int
    model: nn.Module
    optimizer: torch.optim.Optimizer
    data: dict[str, SceneBatches]  # task name -> the client's training batches of that task
    plugins: list[ClientPlugin] = field(default_factory=list)
    task: str = ""  # the task being trained
    # Loss scaling for float16 autocast on a GPU (train.precision=16-mixed); None elsewhere
    # (bf16 and float32 have float32's exponent range: nothing underflows).
    scaler: torch.amp.GradScaler | None = None
    started: int = -1  # the position of the last task whose start the plugins were told

    def __post_init__(self) -> None:
        self.task = self.task or next(iter(self.data))

    @property
    def batches(self) -> SceneBatches:
        return self.data[self.task]

    @property
    def n_samples(self) -> int:
        """Aggregation weight: the client's number of training scenes in the current task."""
        return len(self.batches.positions)

    def state_dict(self) -> dict:
        """Everything the client keeps between rounds (for checkpoints)."""
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "plugins": {p.name: p.state_dict() for p in self.plugins},
            "batches_rng": {t: b.generator.get_state() for t, b in self.data.items()},
            "task": self.task,
            "scaler": None if self.scaler is None else self.scaler.state_dict(),
            "started": self.started,
        }

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        for p in self.plugins:
            p.load_state_dict(state["plugins"].get(p.name, {}))
        for t, rng in state["batches_rng"].items():
            self.data[t].generator.set_state(rng)
        self.task = state["task"]
        # before it was kept, a client had started the task it was on
        self.started = state.get("started", list(self.data).index(self.task))
        if self.scaler is not None and state.get("scaler"):
            self.scaler.load_state_dict(state["scaler"])

    def download(self, weights: dict[str, torch.Tensor]) -> None:
        """Copy the server's tensors into the local model (in place, no reallocation)."""
        state = self.model.state_dict()
        with torch.no_grad():
            for key, value in weights.items():
                state[key].copy_(value)

    def upload(self, keys: list[str]) -> dict[str, torch.Tensor]:
        state = self.model.state_dict()
        return {key: state[key] for key in keys}


def backward(loss: torch.Tensor, scaler, optimizer: torch.optim.Optimizer) -> None:
    """``loss.backward()``; with a ``GradScaler``, of the scaled loss, and the gradients
    unscaled at once, so that plugins (SI, MAS, ...) see the true ones before the step."""
    if scaler is None:
        loss.backward()
        return
    scaler.scale(loss).backward()
    scaler.unscale_(optimizer)


def optimizer_step(optimizer: torch.optim.Optimizer, scaler) -> None:
    """``optimizer.step()``; with a ``GradScaler``, skipped where a gradient is not finite,
    and the scale updated."""
    if scaler is None:
        optimizer.step()
        return
    scaler.step(optimizer)
    scaler.update()


class Stopped(Exception):
    """Local training given up because the run was interrupted meanwhile."""


@dataclass
class LocalStats:
    samples: int = 0  # images (or feature rows) trained on, all epochs, rehearsal included
    loss: float = 0.0  # mean task loss over the round
    figures: Figures = field(default_factory=dict)  # by key: train/loss, train/samples, ...


def train_locally(
    client: Client,
    ctx: LocalContext,
    epochs: int,
    max_batches: int | None = None,
    channels_last: bool = False,
    autocast=contextlib.nullcontext,
    on_epoch=None,
    stop: threading.Event | None = None,
) -> LocalStats:
    """``epochs`` passes over the client's current task (``max_batches`` per epoch at most;
    plugins may ask for fewer passes, and train on their own before them). ``stop``: once
    set, the loop raises :class:`Stopped` at its next step (an interrupted run's clients
    in other threads, see ``ClientPool``)."""
    model, plugins = client.model, client.plugins
    model.train()
    for plugin in plugins:
        plugin.on_round_start(ctx)
    asked = [n for plugin in plugins if (n := plugin.epochs(ctx, epochs)) is not None]
    epochs = min(asked, default=epochs)
    total_loss = torch.zeros((), device=ctx.device)
    seen, first = 0, None  # first: the round's first batch
    for epoch in range(epochs):
        for step, (x, y) in enumerate(client.batches):
            if max_batches is not None and step >= max_batches:
                break
            if stop is not None and stop.is_set():
                raise Stopped(f"client {client.index}: stopped in round {ctx.round}")
            for plugin in plugins:
                x, y = plugin.batch(ctx, x, y)
            if len(x) < 2:  # BatchNorm cannot train on a single sample
                continue
            if channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            task_loss = _step(client, ctx, x, y, autocast)
            first = x if first is None else first
            total_loss += task_loss * len(x)
            seen += len(x)
        if on_epoch is not None:
            on_epoch(epoch + 1)
    for plugin in plugins:
        plugin.on_round_end(ctx)
    stats = round_stats(client, ctx, total_loss, seen)
    per_sample = 0.0 if first is None else flops_per_sample(model, first)
    stats.figures["cost/gflops"] = per_sample * seen / 1e9  # the round's first batch, scaled
    return stats


def flops_per_sample(model: nn.Module, x: torch.Tensor) -> float:
    """The floating-point operations of one training step of ``model`` on batch ``x`` -
    its forward, and its backward to the parameters that train - per sample, counted by
    torch's FlopCounterMode (with :mod:`fedlgr.core.meters.flops`'s formula for a grouped
    convolution's backward pass) on a copy of the model on the meta device: shapes only, nothing
    computed, and the client's own arithmetic untouched (counting on the real step changes
    the rounding of its convolutions). Counted once per model structure, sample shape and
    set of trained parameters (a count takes about four real steps' time)."""
    key = (
        tuple(type(m).__qualname__ for m in model.modules()),
        tuple((name, tuple(p.shape), p.requires_grad) for name, p in model.named_parameters()),
        tuple(x.shape[1:]),
        x.dtype,
    )
    if key not in _COUNTED:
        ghost = _without_hooks(model).to("meta")
        with flop_counter() as counter:
            ghost(torch.empty_like(x, device="meta")).float().sum().backward()
        if len(_COUNTED) >= 64:  # structures seen in one process: a handful
            _COUNTED.clear()
        _COUNTED[key] = counter.get_total_flops() / len(x)
    return _COUNTED[key]


_COUNTED: dict[tuple, float] = {}  # flops_per_sample's counts, by structure and shape

_HOOKS = (
    "_forward_hooks",
    "_forward_hooks_with_kwargs",
    "_forward_hooks_always_called",
    "_forward_pre_hooks",
    "_forward_pre_hooks_with_kwargs",
    "_backward_hooks",
    "_backward_pre_hooks",
)


def _without_hooks(model: nn.Module) -> nn.Module:
    """A copy of ``model`` whose modules have no forward or backward hooks: a hook observes
    the real model (a plug-in, a test's spy) and is no part of its arithmetic. The copy's
    memo maps each hook table to a new empty one, so the model itself is left untouched."""
    memo = {id(getattr(m, name)): OrderedDict() for m in model.modules() for name in _HOOKS}
    return copy.deepcopy(model, memo)


def _step(client: Client, ctx: LocalContext, x, y, autocast) -> torch.Tensor:
    """One optimiser step on the batch ``(x, y)`` with the plugins' hooks; its task loss."""
    model, optimizer, plugins = client.model, client.optimizer, client.plugins
    with autocast():
        union = next((out for p in plugins if (out := p.forward(ctx, x, y)) is not None), None)
        outputs, targets = (model(x), y) if union is None else union
        loss = nn.functional.mse_loss(outputs.float(), targets)
    outputs = outputs[: len(y)].float()
    task_loss = (loss if union is None else nn.functional.mse_loss(outputs, y)).detach()
    for plugin in plugins:
        loss = plugin.loss(ctx, x, y, outputs, loss)
    optimizer.zero_grad(set_to_none=True)
    backward(loss, client.scaler, optimizer)
    for plugin in plugins:
        plugin.before_step(ctx)
    optimizer_step(optimizer, client.scaler)
    for plugin in plugins:
        plugin.after_step(ctx)
    return task_loss


def round_stats(client: Client, ctx: LocalContext, total: torch.Tensor, seen: int) -> LocalStats:
    """The round's samples and mean task loss (the plugins' own training included), checked
    to be finite once per round: no host sync per step."""
    seen += ctx.trained_samples
    mean = (float(total) + ctx.trained_loss) / max(seen, 1)
    if not math.isfinite(mean):
        raise FedlgrError(
            f"round {ctx.round}, client {client.index}: the training loss is {mean} "
            "(not a finite number); lower the learning rates (train.lr_root, train.lr_top; "
            "with FedOpt or FedAvgM the server's too, federated.opt.lr or federated.avgm.lr) "
            "or check the data for extreme values (fedlgr data check)"
        )
    return LocalStats(seen, mean, {"train/loss": mean, "train/samples": float(seen)})
