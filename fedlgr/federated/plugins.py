"""Hooks into a client's local training (Avalanche-style plugins).

A strategy's client-side behaviour (FedProx's proximal term, FedDistill's teacher) and,
later, continual-learning methods are plugins: the local training loop calls every
plugin's hooks, so any of them composes with any strategy and scope. A plugin instance
belongs to one client; everything it keeps is in ``state_dict()`` (in memory, so a resume
feature can checkpoint it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn


@dataclass
class LocalContext:
    """What a plugin may look at during one client's local training in one round."""

    client: int
    round: int
    model: nn.Module
    global_weights: dict[str, torch.Tensor]  # what the client received this round
    device: torch.device
    autocast: object = None  # a context-manager factory for mixed precision
    extra: dict = field(default_factory=dict)


class ClientPlugin:
    """No-op hooks; subclasses override what they need."""

    name = "plugin"

    def on_round_start(self, ctx: LocalContext) -> None:
        """Before the first local step of a round."""

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

    def after_step(self, ctx: LocalContext) -> None:
        """After each optimiser step."""

    def on_round_end(self, ctx: LocalContext) -> None:
        """After the last local step of a round, before the upload."""

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore what ``state_dict`` returned."""
