"""Hooks into a client's local training (Avalanche-style plugins).

A strategy's client-side behaviour (FedProx's proximal term, FedDistill's teacher) and the
continual-learning methods (EWC, SI, MAS, naive rehearsal, FedLGR's latent replay) are
plugins: the local training loop calls every plugin's hooks, so any of them composes with
any strategy and scope without per-combination code. A plugin instance belongs to one
client; everything it keeps is in ``state_dict()`` (in memory, so a resume feature can
checkpoint it).

Order of calls for one client: ``on_task_start`` (the first round of a task the client
trains in, or its end if it trained in none of the task's rounds) ->
``on_round_start`` -> ``epochs`` -> per batch: ``batch`` -> ``forward`` -> ``loss`` ->
backward -> ``before_step`` -> optimiser step -> ``after_step`` -> ``on_round_end`` ->
``payload`` -> (upload, aggregation, download) -> ``round_metrics`` (every round, on the
received model) -> ``on_task_end`` (last round of a task, on the model the client goes on
with) -> ``task_metrics`` (logged with that round).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field

import torch
from torch import nn

from fedlgr.core.data.augment import SceneBatches


@dataclass
class LocalContext:
    """What a plugin may look at during one client's local training in one round."""

    client: int
    round: int
    model: nn.Module
    # What the client received last: its shared tensors as the round found them (views of
    # the model's own tensors, which training then moves: clone what must be kept).
    global_weights: dict[str, torch.Tensor]
    device: torch.device
    autocast: object = contextlib.nullcontext  # a context-manager factory for mixed precision
    task: int = 0  # position of the current task in the schedule
    epochs: int = 1  # local epochs of the round (train.epochs)
    max_batches: int | None = None  # batches per epoch at most (train.max_batches)
    task_name: str = "all"
    batches: SceneBatches | None = None  # the current task's training batches
    optimizer: torch.optim.Optimizer | None = None
    seen: list[SceneBatches] = field(default_factory=list)  # every task's batches so far
    trained_samples: int = 0  # samples a plugin trained on outside the batch loop
    trained_loss: float = 0.0  # their summed task loss
    scaler: torch.amp.GradScaler | None = None  # the client's (client.backward / step)
    # What the strategy sent this client for the round besides the global tensors
    # (Strategy.payload: SCAFFOLD's control variate); empty when it sends nothing.
    received: dict[str, torch.Tensor] = field(default_factory=dict)

    def plain_batches(
        self, batch_size: int | None = None, batches: SceneBatches | None = None
    ) -> SceneBatches:
        """The current task's scenes (or ``batches``' scenes) in order, normalised but not
        augmented, once each."""
        b = self.batches if batches is None else batches
        return SceneBatches(
            b.inputs,
            b.targets,
            b.positions.numpy(),
            batch_size or b.batch_size,
            shuffle=False,
            device=b.device,
        )


class ClientPlugin:
    """No-op hooks; subclasses override what they need."""

    name = "plugin"

    @classmethod
    def from_settings(cls, settings, continual, seed: int) -> ClientPlugin:
        """A continual-learning method's plugin for one client: ``settings`` is its section
        (``continual.<method>``, None where it has none), ``continual`` the whole
        ``continual`` section (``importance_batches``, ...), ``seed`` the client's own."""
        return cls()

    def on_task_start(self, ctx: LocalContext) -> None:
        """Before the first round of a task."""

    def on_round_start(self, ctx: LocalContext) -> None:
        """Before the first local step of a round."""

    metric_names: tuple[str, ...] = ()  # what ``task_metrics`` reports (MLflow: name/key)

    def epochs(self, ctx: LocalContext, epochs: int) -> int | None:
        """How many passes the batch loop makes this round instead of ``epochs``; ``None``:
        no opinion (the smallest answer wins)."""
        return None

    def batch(
        self, ctx: LocalContext, x: torch.Tensor, y: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The batch to train on (e.g. with rehearsal samples mixed in)."""
        return x, y

    def forward(
        self, ctx: LocalContext, x: torch.Tensor, y: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(outputs, targets) to train on, whose first ``len(y)`` rows are the batch's own;
        ``None``: the model's outputs on ``x`` and ``y`` (one plugin at most answers)."""
        return None

    def loss(
        self,
        ctx: LocalContext,
        x: torch.Tensor,
        y: torch.Tensor,
        outputs: torch.Tensor,
        loss: torch.Tensor,
    ) -> torch.Tensor:
        """The loss to back-propagate, given the task loss so far (add a penalty, mix in a
        teacher's outputs, ...). Called in plugin order before ``backward``."""
        return loss

    def before_step(self, ctx: LocalContext) -> None:
        """After ``backward``, before the optimiser step (gradients are in ``.grad``)."""

    def after_step(self, ctx: LocalContext) -> None:
        """After each optimiser step."""

    def on_round_end(self, ctx: LocalContext) -> None:
        """After the last local step of a round, before the upload."""

    def payload(self, ctx: LocalContext) -> dict[str, torch.Tensor]:
        """What this plugin sends the server with the round's upload, besides the shared
        tensors (SCAFFOLD: the change of the client's control variate), read by its
        strategy's ``take_payloads``; nothing by default."""
        return {}

    def on_task_end(self, ctx: LocalContext) -> None:
        """After the last round of a task (aggregation included): importance, memories,
        generators are updated here."""

    def round_metrics(self, ctx: LocalContext) -> dict[str, float]:
        """Diagnostics measured after every round's download, before any task end (names
        from ``metric_names``); not billed to the client's costs either."""
        return {}

    def task_metrics(self, ctx: LocalContext) -> dict[str, float]:
        """Diagnostics measured right after ``on_task_end`` (names from ``metric_names``);
        not billed to the client's costs: they are the experimenter's, not the method's."""
        return {}

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore what ``state_dict`` returned."""
