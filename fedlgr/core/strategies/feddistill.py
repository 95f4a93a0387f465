"""FedDistill: a personalised local teacher distilled into the shared student.

Each client keeps a teacher - a model of the same architecture trained only on the
client's own shard and never sent anywhere - and trains it alongside the student, batch
by batch. The student, which is what gets aggregated, learns from the labels and from the
teacher's outputs: loss = (1 - a) MSE(student, y) + a MSE(student, teacher), a =
``federated.distill.weight``. (The paper's reference code trains the teacher centrally;
here each client's teacher sees its own data only.)
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from fedlgr.core.client.plugins import ClientPlugin, LocalContext
from fedlgr.core.strategies.base import Strategy


class Teacher(ClientPlugin):
    name = "feddistill"

    def __init__(self, weight: float):
        self.weight = weight
        self.model: nn.Module | None = None
        self.optimizer: torch.optim.Optimizer | None = None
        self._restored: dict | None = None  # a checkpoint's teacher, until there is a model

    def on_round_start(self, ctx: LocalContext) -> None:
        if self.model is None:  # born from the client's first model, then on its own
            self.model = copy.deepcopy(ctx.model)
            self.optimizer = self.model.configure_optimizers()
            if self._restored is not None:
                self.model.load_state_dict(self._restored["model"])
                self.optimizer.load_state_dict(self._restored["optimizer"])
                self._restored = None
        self.model.train()

    def loss(self, ctx, x, y, outputs, loss):
        with ctx.autocast():
            taught = self.model(x)
            teacher_loss = nn.functional.mse_loss(taught.float(), y)
        self.optimizer.zero_grad(set_to_none=True)
        teacher_loss.backward()
        self.optimizer.step()
        distill = nn.functional.mse_loss(outputs, taught.detach().float())
        return (1 - self.weight) * loss + self.weight * distill

    def state_dict(self) -> dict:
        if self.model is None:
            return self._restored or {}
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """A teacher is built from the client's model at its first round: until then the
        state waits (a run resumed from a checkpoint has no teacher yet)."""
        if not state:
            return
        if self.model is None:
            self._restored = state
        else:
            self.model.load_state_dict(state["model"])
            self.optimizer.load_state_dict(state["optimizer"])


class FedDistill(Strategy):
    client_plugin_types = (Teacher,)

    def client_plugins(self, client: int) -> list[ClientPlugin]:
        return [Teacher(self.settings.weight)]
