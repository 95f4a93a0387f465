"""FedProx (Li et al. 2020): each client minimises its loss + mu/2 ||w - w_global||^2.

The proximal term runs over the parameters the client received this round (the shared,
trainable tensors), so under FedRoot it anchors the root only. The paper's reference code
omits the term; here it really is added to the client loss.
"""

from __future__ import annotations

import torch

from fedlgr.core.client.plugins import ClientPlugin, LocalContext
from fedlgr.core.strategies.base import Strategy


class ProximalTerm(ClientPlugin):
    name = "fedprox"

    def __init__(self, mu: float):
        self.mu = mu
        self.anchors: list[tuple[torch.Tensor, torch.Tensor]] = []

    def on_round_start(self, ctx: LocalContext) -> None:
        params = dict(ctx.model.named_parameters())
        self.anchors = [
            (params[k], w.detach().clone()) for k, w in ctx.global_weights.items() if k in params
        ]

    def loss(self, ctx, x, y, outputs, loss):
        if self.mu == 0 or not self.anchors:
            return loss
        prox = sum(torch.sum((p - anchor) ** 2) for p, anchor in self.anchors)
        return loss + 0.5 * self.mu * prox

    def on_round_end(self, ctx: LocalContext) -> None:
        self.anchors = []  # the anchors are this round's global weights only


class FedProx(Strategy):
    client_plugin_types = (ProximalTerm,)

    def client_plugins(self, client: int) -> list[ClientPlugin]:
        return [ProximalTerm(self.settings.mu)]
