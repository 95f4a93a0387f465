"""MAS, Memory Aware Synapses (Aljundi et al. 2018).

Importance of each parameter (``continual.mas.importance``):

* ``sample`` (default, Aljundi et al., eq. 4): the mean over the task's training scenes of
  the absolute gradient of each scene's squared L2 output norm, ||f(x_k)||^2 (no labels);
* ``batch``: fedlgr's earlier form, kept to reproduce runs made with it: the absolute
  gradient of each mini-batch's mean squared norm, averaged over batches (as Avalanche's
  plug-in does); not a constant factor of the per-scene importance, so no lambda makes the
  two alike (docs/fedlgr.md, "EWC's lambda").

Importances accumulate over tasks (summed); the penalty is lambda * sum_i Omega_i (theta_i -
theta*_i)^2 with theta* the latest task's parameters (Aljundi et al., eq. 9).
"""

from __future__ import annotations

import torch

from fedlgr.core.client.plugins import LocalContext
from fedlgr.core.continual.penalty import (
    QuadraticPenalty,
    gradient_importance,
    per_sample_importance,
    snapshot,
)


def _squared_norm(out: torch.Tensor, y: torch.Tensor, extra: torch.Tensor) -> torch.Tensor:
    return out.pow(2).sum()


def output_norm_importance(
    model, batches, max_batches: int | None = None, kind: str = "sample"
) -> dict[str, torch.Tensor]:
    if kind == "batch":
        return gradient_importance(
            model, batches, lambda out, y: out.pow(2).sum(dim=1).mean(), torch.abs, max_batches
        )
    return per_sample_importance(model, batches, _squared_norm, torch.abs, max_batches)


class MAS(QuadraticPenalty):
    name = "mas"

    def __init__(self, lam: float, max_batches: int | None = None, kind: str = "sample"):
        super().__init__(lam)
        self.max_batches, self.kind = max_batches, kind

    @classmethod
    def from_settings(cls, settings, continual, seed: int) -> MAS:
        return cls(settings.lambda_, continual.importance_batches, settings.importance)

    def on_task_end(self, ctx: LocalContext) -> None:
        new = output_norm_importance(ctx.model, ctx.plain_batches(), self.max_batches, self.kind)
        if self.terms:
            old, _ = self.terms[0]
            new = {n: old[n] + w for n, w in new.items()}
        self.terms = [(new, snapshot(ctx.model))]
