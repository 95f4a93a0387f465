"""EWC (Kirkpatrick et al. 2017) and EWC-Online (Schwarz et al. 2018) for regression.

At the end of each task, the diagonal Fisher information of the client's model is
estimated on that task's training scenes and the parameters are kept as the anchor.

* ``ewc_fisher=empirical`` (default): squared gradients of the MSE between the model's
  outputs and the *labels* (the empirical Fisher);
* ``ewc_fisher=model``: squared gradients of the MSE to targets drawn from the model's own
  predictive distribution, outputs + N(0, 1) noise (the Fisher of a unit-variance Gaussian
  likelihood, without using the labels).

Gradients are per mini-batch and averaged over batches. EWC keeps one penalty term per past
task: lambda * sum_t sum_i F_t,i (theta_i - theta*_t,i)^2. EWC-Online keeps one running
Fisher, F <- gamma F + F_new, anchored at the latest task's parameters.
"""

from __future__ import annotations

import torch
from torch import nn

from fedlgr.core.client.plugins import LocalContext
from fedlgr.core.continual.penalty import QuadraticPenalty, gradient_importance, snapshot


def fisher(
    model: nn.Module,
    batches,
    kind: str = "empirical",
    max_batches: int | None = None,
    generator: torch.Generator | None = None,
) -> dict[str, torch.Tensor]:
    """Diagonal Fisher estimate (see the module docstring for ``kind``)."""
    if kind == "empirical":
        objective = nn.functional.mse_loss
    else:

        def objective(outputs, y):
            noise = torch.randn(outputs.shape, generator=generator).to(outputs.device)
            return nn.functional.mse_loss(outputs, (outputs + noise).detach())

    return gradient_importance(model, batches, objective, torch.square, max_batches)


class EWC(QuadraticPenalty):
    name = "ewc"

    def __init__(
        self, lam: float, kind: str = "empirical", max_batches: int | None = None, seed: int = 0
    ):
        super().__init__(lam)
        self.kind, self.max_batches = kind, max_batches
        self.generator = torch.Generator().manual_seed(seed)

    @classmethod
    def from_settings(cls, settings, continual, seed: int) -> EWC:
        return cls(settings.lambda_, settings.fisher, continual.importance_batches, seed)

    def estimate(self, ctx: LocalContext) -> dict[str, torch.Tensor]:
        return fisher(ctx.model, ctx.plain_batches(), self.kind, self.max_batches, self.generator)

    def on_task_end(self, ctx: LocalContext) -> None:
        self.terms.append((self.estimate(ctx), snapshot(ctx.model)))

    def state_dict(self) -> dict:
        return {**super().state_dict(), "rng": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        if "rng" in state:
            self.generator.set_state(state["rng"])


class EWCOnline(EWC):
    name = "ewc_online"

    def __init__(
        self,
        lam: float,
        gamma: float,
        kind: str = "empirical",
        max_batches: int | None = None,
        seed: int = 0,
    ):
        super().__init__(lam, kind, max_batches, seed)
        self.gamma = gamma

    @classmethod
    def from_settings(cls, settings, continual, seed: int) -> EWCOnline:
        s = settings  # continual.ewc: EWC-Online shares EWC's settings
        return cls(s.lambda_, s.gamma, s.fisher, continual.importance_batches, seed)

    def on_task_end(self, ctx: LocalContext) -> None:
        new = self.estimate(ctx)
        if self.terms:
            old, _ = self.terms[0]
            new = {n: self.gamma * old[n] + f for n, f in new.items()}
        self.terms = [(new, snapshot(ctx.model))]
