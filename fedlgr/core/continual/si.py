"""SI, Synaptic Intelligence (Zenke et al. 2017).

During a task every optimiser step adds, per parameter, ``-g * delta`` to a running path
integral omega (g: the gradient that step used, delta: the change the step made). At the
end of the task the importance grows by ``max(omega / (Delta^2 + xi), 0)`` with Delta the
parameter's total change over the task and xi the damping; parameters that did not move
gain nothing. The penalty is c * sum_i Omega_i (theta_i - theta*_i)^2.
"""

from __future__ import annotations

import torch

from fedlgr.core.client.plugins import LocalContext
from fedlgr.core.continual.penalty import QuadraticPenalty, snapshot


class SI(QuadraticPenalty):
    name = "si"

    def __init__(self, c: float, xi: float):
        super().__init__(c)
        self.xi = xi
        self.omega: dict[str, torch.Tensor] = {}
        self.start: dict[str, torch.Tensor] = {}
        self._before: dict[str, torch.Tensor] = {}
        self._grads: dict[str, torch.Tensor] = {}

    @classmethod
    def from_settings(cls, settings, continual, seed: int) -> SI:
        return cls(settings.c, settings.xi)

    def on_task_start(self, ctx: LocalContext) -> None:
        self.start = snapshot(ctx.model)
        self.omega = {n: torch.zeros_like(p) for n, p in self.start.items()}

    def before_step(self, ctx: LocalContext) -> None:
        self._before, self._grads = {}, {}
        for n, p in ctx.model.named_parameters():
            if p.grad is not None and n in self.omega:
                self._before[n] = p.detach().clone()
                self._grads[n] = p.grad.detach().clone()

    def after_step(self, ctx: LocalContext) -> None:
        params = dict(ctx.model.named_parameters())
        for n, before in self._before.items():
            self.omega[n] -= self._grads[n] * (params[n].detach() - before)
        self._before, self._grads = {}, {}

    def on_task_end(self, ctx: LocalContext) -> None:
        end = snapshot(ctx.model)
        gained = {
            n: torch.clamp(self.omega[n] / ((end[n] - self.start[n]) ** 2 + self.xi), min=0.0)
            for n in end
        }
        if self.terms:
            old, _ = self.terms[0]
            gained = {n: old[n] + w for n, w in gained.items()}
        self.terms = [(gained, end)]

    def state_dict(self) -> dict:
        return {**super().state_dict(), "omega": dict(self.omega), "start": dict(self.start)}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.omega, self.start = dict(state.get("omega", {})), dict(state.get("start", {}))
