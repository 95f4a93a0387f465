"""MAS, Memory Aware Synapses (Aljundi et al. 2018).

Importance of each parameter: the mean absolute gradient of the squared L2 norm of the
model's outputs, ||f(x)||^2, over the task's training scenes (no labels needed; per
mini-batch, as in Avalanche). Importances accumulate over tasks (summed); the penalty is
lambda * sum_i Omega_i (theta_i - theta*_i)^2 with theta* the latest task's parameters.
"""

from __future__ import annotations

import torch

from fedlgr.core.client.plugins import LocalContext
from fedlgr.core.continual.penalty import QuadraticPenalty, gradient_importance, snapshot


def output_norm_importance(
    model, batches, max_batches: int | None = None
) -> dict[str, torch.Tensor]:
    return gradient_importance(
        model, batches, lambda out, y: out.pow(2).sum(dim=1).mean(), torch.abs, max_batches
    )


class MAS(QuadraticPenalty):
    name = "mas"

    def __init__(self, lam: float, max_batches: int | None = None):
        super().__init__(lam)
        self.max_batches = max_batches

    @classmethod
    def from_settings(cls, settings, continual, seed: int) -> MAS:
        return cls(settings.lambda_, continual.importance_batches)

    def on_task_end(self, ctx: LocalContext) -> None:
        new = output_norm_importance(ctx.model, ctx.plain_batches(), self.max_batches)
        if self.terms:
            old, _ = self.terms[0]
            new = {n: old[n] + w for n, w in new.items()}
        self.terms = [(new, snapshot(ctx.model))]
