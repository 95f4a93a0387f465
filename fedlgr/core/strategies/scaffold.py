"""SCAFFOLD (Karimireddy et al., ICML 2020): control variates that correct client drift.

The server keeps a control variate ``c`` and each client its own ``c_i`` (zeros at
first). Each chosen client receives ``c`` with the round (the strategy's payload), corrects
every local gradient to ``g - c_i + c`` before its optimiser's step, and after its ``K``
local steps from the global ``x`` to ``y_i`` updates its control variate by option II,
``c_i+ = c_i - c + (x - y_i) / (K lr_l)`` (``lr_l``: each parameter's local learning rate,
its optimiser group's), and sends ``Delta c_i = c_i+ - c_i`` besides its tensors. The
server steps ``x <- x + lr (mean(y_i) - x)`` (``federated.scaffold.lr``, the global
learning rate; the mean is the sample-weighted one of every fedlgr strategy) and
``c <- c + sum(Delta c_i) / N`` over the ``N`` clients of the run (Algorithm 1).

Control variates exist for the shared trainable parameters only: under FedRoot
(``method=FedRootSCAFFOLD``) for the root's; BatchNorm running statistics are averaged as
in FedAvg. fedlgr's clients train with Adam where the paper's take SGD steps; the
correction is added to the gradient Adam receives (docs/methods.md).
"""

from __future__ import annotations

import math

import torch

from fedlgr.core.client.plugins import ClientPlugin, LocalContext
from fedlgr.core.strategies.base import ServerOptimizer, Weights

PREFIX = "scaffold/"  # the payload's keys: scaffold/<parameter>
# How far a control-variate change may lie off its update's direction, as a share of its
# norm, and K below the fewest steps (Scaffold.payload_refusal).
PARALLEL = 1e-3


class ControlVariate(ClientPlugin):
    """A client's control variate ``c_i`` and its correction of the local gradients."""

    name = "scaffold"

    def __init__(self):
        self.own: Weights = {}  # c_i, kept across rounds
        self.delta: Weights = {}  # this round's Delta c_i, sent with the upload
        self._start: Weights = {}  # x: the parameters as the round found them
        self._server: Weights = {}  # c, as received this round
        self._params: dict[str, torch.nn.Parameter] = {}
        self._lrs: dict[str, float] = {}
        self._steps = 0

    def on_round_start(self, ctx: LocalContext) -> None:
        params = dict(ctx.model.named_parameters())
        self._params = {k: params[k] for k in ctx.global_weights if k in params}
        self._start = {k: p.detach().clone() for k, p in self._params.items()}
        zeros = {k: torch.zeros_like(p) for k, p in self._start.items()}
        self.own = {k: self.own.get(k, z).to(z) for k, z in zeros.items()}
        self._server = {k: ctx.received.get(PREFIX + k, z).to(z) for k, z in zeros.items()}
        lrs = {id(p): g["lr"] for g in ctx.optimizer.param_groups for p in g["params"]}
        self._lrs = {k: lrs[id(p)] for k, p in self._params.items()}
        self._steps = 0

    def before_step(self, ctx: LocalContext) -> None:
        for k, p in self._params.items():
            if p.grad is not None:
                p.grad.add_(self._server[k] - self.own[k])

    def after_step(self, ctx: LocalContext) -> None:
        self._steps += 1

    def on_round_end(self, ctx: LocalContext) -> None:
        """Option II: ``c_i+ = c_i - c + (x - y_i) / (K lr_l)``; nothing moves without a
        step (or at a learning rate of 0)."""
        self.delta = {}
        for k, p in self._params.items():
            scale = self._steps * self._lrs[k]
            if scale == 0:
                self.delta[k] = torch.zeros_like(self.own[k])
                continue
            new = self.own[k] - self._server[k] + (self._start[k] - p.detach()) / scale
            self.delta[k], self.own[k] = new - self.own[k], new

    def payload(self, ctx: LocalContext) -> Weights:
        return {PREFIX + k: d for k, d in self.delta.items()}

    def state_dict(self) -> dict:
        return {"own": dict(self.own)}

    def load_state_dict(self, state: dict) -> None:
        self.own = dict(state.get("own", {}))


class Scaffold(ServerOptimizer):
    """The server's half: ``c``, sent to every chosen client, and the global step."""

    client_plugin_types = (ControlVariate,)

    def __init__(self, config):
        super().__init__(config)
        self.control: Weights = {}  # c

    def bind(self, shared: list[str], parameters: set[str], initial: Weights | None = None) -> None:
        super().bind(shared, parameters, initial)
        self.control = {k: torch.zeros_like(initial[k]) for k in shared if k in self.trainable}

    def client_plugins(self, client: int) -> list[ClientPlugin]:
        return [ControlVariate()]

    def payload(self, client: int) -> Weights:
        return {PREFIX + k: c for k, c in self.control.items()}

    def payload_template(self) -> Weights:
        return {PREFIX + k: torch.zeros_like(c) for k, c in self.control.items()}

    def step(self, key: str, weight: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        return weight + self.settings.lr * delta

    def payload_refusal(
        self, result, shared: Weights, steps: int, learning_rates: dict[str, float]
    ) -> str | None:
        """Option II fixes the change a client sends: ``Delta c_i + c = (x - y_i) / (K lr)``,
        its update's direction, K the local steps - at least ``steps``. So with ``w = (Delta
        c_i + c) lr`` and ``v = x - y_i`` the server checks that w is ``v / K``: off v's line
        by at most :data:`PARALLEL` of its norm (float32 rounding on the client), K not below
        ``steps``. A payload scaled x8 is off the line once c is not 0, and claims K / 8
        steps while c is (round 1)."""
        if any(learning_rates[k] == 0 for k in self.control):
            return None  # nothing moves: option II sends 0
        dot = vv = ww = 0.0
        for k, c in self.control.items():
            w = (result.payload[PREFIX + k].double() + c.double()) * learning_rates[k]
            v = shared[k].double() - result.weights[k].double()
            dot += float((w * v).sum())
            vv += float(v.pow(2).sum())
            ww += float(w.pow(2).sum())
        if vv == 0 or ww == 0:  # no step moved it (Delta c_i = -c), or no step was taken
            return None if ww == 0 else "scaffold payload moves where the parameters did not"
        off = math.sqrt(max(0.0, ww - dot * dot / vv) / ww)
        if dot <= 0 or off > PARALLEL:
            return (
                "scaffold payload is not its update's control-variate change (off its "
                f"direction by {off:.2g} of its norm)"
            )
        k_steps = vv / dot
        if k_steps < steps * (1 - PARALLEL):
            return (
                f"scaffold payload is that of {k_steps:.3g} local steps, fewer than the "
                f"{steps} its {result.n_samples} scenes train"
            )
        return None

    def take_payloads(self, sums: Weights, senders: int, clients: int) -> None:
        for k, c in self.control.items():
            change = sums[PREFIX + k].to(c.device) / clients
            self.control[k] = (c.double() + change).to(c.dtype)

    def state_dict(self) -> dict:
        return {"control": dict(self.control)}

    def load_state_dict(self, state: dict) -> None:
        self.control = dict(state["control"])
