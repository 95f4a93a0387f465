"""SI, Synaptic Intelligence (Zenke et al. 2017).

During a task every optimiser step adds, per parameter, ``-g * delta`` to a running path
integral omega (g: the gradient of the loss that step followed, delta: the change the step
made). At the end of the task the importance grows by ``omega / (Delta^2 + xi)`` with
Delta the parameter's total change over the task and xi the damping (Zenke et al., eq. 5);
parameters that did not move gain nothing. The penalty is c * sum_i Omega_i (theta_i -
theta*_i)^2 (eq. 4).

As published (and in the authors' code, ganguli-lab/pathint: ``unreg_grads``), g is the
gradient of the loss *without* SI's own penalty: omega measures how much a parameter
lowered the loss. The penalty's gradient, ``2 c sum Omega (theta - theta*)``, is known in
closed form and taken off the step's gradient. An optimiser step that does not follow the
gradient (Adam's) can make omega negative, and so a parameter's importance; eq. 5 keeps it,
though a negative importance rewards a weight for leaving its anchor: each task's end logs
the share of importances below 0 (``si/negative``), and ``clamp=total`` is the safe form.

fedlgr's earlier forms stay as settings, to reproduce runs made with them:
``continual.si.clamp=task`` (each task's gain clamped at 0) and
``continual.si.path_gradient=loss+penalty`` (g including SI's penalty). ``clamp=total``
clamps the summed importance at 0 after each task, as the authors' code does
(``tf.nn.relu`` of the running sum in pathint/protocols.py), not their paper.
"""

from __future__ import annotations

import torch

from fedlgr.core.client.plugins import LocalContext
from fedlgr.core.continual.penalty import QuadraticPenalty, snapshot


class SI(QuadraticPenalty):
    name = "si"
    metric_names = ("negative",)  # the share of importances below 0 after a task's end

    def __init__(self, c: float, xi: float, clamp: str = "none", path_gradient: str = "loss"):
        super().__init__(c)
        self.xi, self.clamp, self.path_gradient = xi, clamp, path_gradient
        self.omega: dict[str, torch.Tensor] = {}
        self.start: dict[str, torch.Tensor] = {}
        self._before: dict[str, torch.Tensor] = {}
        self._grads: dict[str, torch.Tensor] = {}

    @classmethod
    def from_settings(cls, settings, continual, seed: int) -> SI:
        return cls(settings.c, settings.xi, settings.clamp, settings.path_gradient)

    def on_task_start(self, ctx: LocalContext) -> None:
        self.start = snapshot(ctx.model)
        self.omega = {n: torch.zeros_like(p) for n, p in self.start.items()}

    def penalty_gradient(self, name: str, param: torch.Tensor) -> torch.Tensor | None:
        """d penalty / d param: ``2 c sum_terms Omega (param - anchor)`` (None: no penalty)."""
        if not self.terms or self.coefficient == 0:
            return None
        total = sum(w[name] * (param - a[name]) for w, a in self.terms if name in w)
        return 2 * self.coefficient * total

    def before_step(self, ctx: LocalContext) -> None:
        self._before, self._grads = {}, {}
        for n, p in ctx.model.named_parameters():
            if p.grad is not None and n in self.omega:
                g = p.grad.detach().clone()
                own = None
                if self.path_gradient == "loss":
                    own = self.penalty_gradient(n, p.detach())
                self._before[n] = p.detach().clone()
                self._grads[n] = g if own is None else g - own

    def after_step(self, ctx: LocalContext) -> None:
        params = dict(ctx.model.named_parameters())
        for n, before in self._before.items():
            self.omega[n] -= self._grads[n] * (params[n].detach() - before)
        self._before, self._grads = {}, {}

    def on_task_end(self, ctx: LocalContext) -> None:
        end = snapshot(ctx.model)
        gained = {n: self.omega[n] / ((end[n] - self.start[n]) ** 2 + self.xi) for n in end}
        if self.clamp == "task":
            gained = {n: torch.clamp(w, min=0.0) for n, w in gained.items()}
        if self.terms:
            old, _ = self.terms[0]
            gained = {n: old[n] + w for n, w in gained.items()}
        if self.clamp == "total":
            gained = {n: torch.clamp(w, min=0.0) for n, w in gained.items()}
        self.terms = [(gained, end)]

    def task_metrics(self, ctx: LocalContext) -> dict[str, float]:
        importance = self.terms[0][0].values() if self.terms else ()
        below = sum(int((w < 0).sum()) for w in importance)
        return {"negative": below / max(sum(w.numel() for w in importance), 1)}

    def state_dict(self) -> dict:
        return {**super().state_dict(), "omega": dict(self.omega), "start": dict(self.start)}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.omega, self.start = dict(state.get("omega", {})), dict(state.get("start", {}))
