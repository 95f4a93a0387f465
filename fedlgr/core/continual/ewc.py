"""EWC (Kirkpatrick et al. 2017) and EWC-Online (Schwarz et al. 2018) for regression.

At the end of each task, the diagonal Fisher information of the client's model is
estimated on that task's training scenes and the parameters are kept as the anchor.
The Fisher is the mean over the task's scenes of each scene's squared gradient
(``continual.ewc.fisher``):

* ``empirical`` (default): of the scene's training loss, the MSE between its outputs and
  its *labels* (the empirical Fisher, as Kirkpatrick et al. estimate it);
* ``model``: of the MSE to targets drawn from the model's own predictive distribution,
  outputs + N(0, 2^2) noise per action (one Monte-Carlo draw of the true Fisher, without
  using the labels).

The likelihood is the one whose negative log is the training loss: the MSE over the 8
actions, (1/8) sum_a (f_a - y_a)^2, is a Gaussian of variance 4 per action, hence the
noise's variance. The penalty then weighs the past task's Fisher in the units of the
loss it is added to, as Kirkpatrick et al.'s lambda does. (A unit-variance Gaussian's
Fisher, sum_a (f_a - y_a) grad f_a squared, is 16x this one.)

* ``batch``: fedlgr's earlier form, kept to reproduce runs made with it (and its lambda,
  100): the squared gradient of each mini-batch's mean loss, averaged over batches, and the
  penalty without the 1/2. It is about 1/batch-size of the per-scene Fisher, so its
  lambdas mean something else (docs/fedlgr.md, "EWC's lambda");
* ``batch_model``: fedlgr's earlier ``model``, the same way per mini-batch, to outputs +
  N(0, 1) noise.

EWC keeps one penalty term per past task, (lambda / 2) sum_t sum_i F_t,i (theta_i -
theta*_t,i)^2 (Kirkpatrick et al., eq. 3). EWC-Online keeps one running Fisher,
F <- gamma F + F_new, anchored at the latest task's parameters (Schwarz et al., eq. 8).
"""

from __future__ import annotations

import torch
from torch import nn

from fedlgr.core.client.plugins import LocalContext
from fedlgr.core.continual.penalty import (
    QuadraticPenalty,
    gradient_importance,
    per_sample_importance,
    snapshot,
)

BATCH_KINDS = ("batch", "batch_model")  # fedlgr's earlier forms: no 1/2 in the penalty
# the standard deviation of the Gaussian whose negative log-likelihood is the MSE over the
# actions, (1/8) sum (f - y)^2 = sum (f - y)^2 / (2 x 2^2)
LIKELIHOOD_STD = 2.0


def _scene_loss(out: torch.Tensor, y: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """One scene's training loss: the MSE over its actions."""
    return nn.functional.mse_loss(out, y)


def _sampled_loss(out: torch.Tensor, y: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """One scene's MSE to a target drawn from the model: its outputs plus ``noise``."""
    return nn.functional.mse_loss(out, (out + noise).detach())


def fisher(
    model: nn.Module,
    batches,
    kind: str = "empirical",
    max_batches: int | None = None,
    generator: torch.Generator | None = None,
) -> dict[str, torch.Tensor]:
    """Diagonal Fisher estimate (see the module docstring for ``kind``)."""
    if kind == "batch":
        return gradient_importance(
            model, batches, nn.functional.mse_loss, torch.square, max_batches
        )
    if kind == "batch_model":

        def to_a_draw(outputs: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            noise = torch.randn(outputs.shape, generator=generator).to(outputs.device)
            return nn.functional.mse_loss(outputs, (outputs + noise).detach())

        return gradient_importance(model, batches, to_a_draw, torch.square, max_batches)
    if kind == "empirical":
        return per_sample_importance(model, batches, _scene_loss, torch.square, max_batches)

    def noise(y: torch.Tensor) -> torch.Tensor:  # the loss's likelihood: variance 4
        return (LIKELIHOOD_STD * torch.randn(y.shape, generator=generator)).to(y.device)

    return per_sample_importance(model, batches, _sampled_loss, torch.square, max_batches, noise)


class EWC(QuadraticPenalty):
    name = "ewc"

    def __init__(
        self, lam: float, kind: str = "empirical", max_batches: int | None = None, seed: int = 0
    ):
        # Kirkpatrick et al.'s lambda / 2; fedlgr's earlier batch forms have no 1/2
        super().__init__(lam if kind in BATCH_KINDS else lam / 2)
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
