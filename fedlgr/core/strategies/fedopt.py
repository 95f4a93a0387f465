"""FedOpt as FedAdam (Reddi et al. 2021, Algorithm 2): server-side Adam on the mean update.

With x the global weights and Delta = mean(client weights) - x:
m <- b1 m + (1 - b1) Delta;  v <- b2 v + (1 - b2) Delta^2;  x <- x + eta m / (sqrt(v) + tau)
(no bias correction, as published). Trainable parameters take the Adam step; BatchNorm
running statistics, which are not parameters, are averaged as in FedAvg. The paper's
reference code never runs this server step; here it does.
"""

from __future__ import annotations

import torch

from fedlgr.core.strategies.base import ServerOptimizer, Weights


class FedOpt(ServerOptimizer):
    def __init__(self, config):
        super().__init__(config)
        self.m: Weights = {}
        self.v: Weights = {}

    def step(self, key: str, weight: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        (b1, b2), eta, tau = self.settings.betas, self.settings.lr, self.settings.tau
        m = self.m.get(key, torch.zeros_like(delta)).mul_(b1).add_(delta, alpha=1 - b1)
        v = self.v.get(key, torch.zeros_like(delta)).mul_(b2).addcmul_(delta, delta, value=1 - b2)
        self.m[key], self.v[key] = m, v
        return weight + eta * m / (v.sqrt() + tau)

    def state_dict(self) -> dict:
        return {"m": dict(self.m), "v": dict(self.v)}

    def load_state_dict(self, state: dict) -> None:
        self.m, self.v = dict(state["m"]), dict(state["v"])
