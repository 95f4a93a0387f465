"""LwF, Learning without Forgetting (Li & Hoiem 2016), for regression.

At the start of every task after the first, the client keeps a frozen copy of its model
as it is then (the previous tasks' model). While it trains on the new task, its outputs on
the new task's scenes are pulled towards that copy's outputs on the same scenes:

``loss = task loss + alpha * mean over batch and actions (f(x) - f_start(x))^2``

The paper distils the old tasks' heads with a temperature-softened cross-entropy; here
all tasks share one head of 8 appropriateness scores (regression), so the distillation is
the mean squared difference of the outputs, and there is no temperature. The copy's
BatchNorm layers are in eval mode (its running statistics, not the batch's). No data of
past tasks is kept, only the copy, and it never leaves the client.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from fedlgr.core.client.plugins import ClientPlugin, LocalContext
from fedlgr.core.methods import LwFSettings


class LwF(ClientPlugin):
    name = "lwf"

    def __init__(self, alpha: float):
        self.alpha = alpha
        self.previous: nn.Module | None = None  # the model at the start of this task
        self._restored: dict | None = None  # a checkpoint's copy, until there is a model

    @classmethod
    def from_settings(cls, settings: LwFSettings, continual, seed: int) -> LwF:
        return cls(settings.alpha)

    def on_task_start(self, ctx: LocalContext) -> None:
        self.previous = None if ctx.task == 0 else self._frozen(ctx.model)
        self._restored = None

    def on_round_start(self, ctx: LocalContext) -> None:
        if self._restored is not None:  # resumed within a task: the copy from the checkpoint
            self.previous = self._frozen(ctx.model)
            self.previous.load_state_dict(self._restored["previous"])
            self._restored = None

    @staticmethod
    def _frozen(model: nn.Module) -> nn.Module:
        frozen = copy.deepcopy(model).eval()
        frozen.requires_grad_(False)
        return frozen

    def loss(self, ctx, x, y, outputs, loss):
        if self.previous is None or self.alpha == 0:
            return loss
        with torch.no_grad(), ctx.autocast():
            start = self.previous(x).float()
        return loss + self.alpha * nn.functional.mse_loss(outputs, start)

    def state_dict(self) -> dict:
        if self.previous is None:
            return self._restored or {}
        return {"previous": self.previous.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.previous, self._restored = None, (state or None)
