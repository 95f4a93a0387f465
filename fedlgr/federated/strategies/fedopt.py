"""FedOpt as FedAdam (Reddi et al. 2021, Algorithm 2): server-side Adam on the mean update.

With x the global weights and Delta = mean(client weights) - x:
m <- b1 m + (1 - b1) Delta;  v <- b2 v + (1 - b2) Delta^2;  x <- x + eta m / (sqrt(v) + tau)
(no bias correction, as published). Trainable parameters take the Adam step; BatchNorm
running statistics, which are not parameters, are averaged as in FedAvg. The paper's
reference code never runs this server step; here it does.
"""

from __future__ import annotations

import torch

from fedlgr.federated.strategies.base import Strategy, Weights


class FedOpt(Strategy):
    def __init__(self, config):
        super().__init__(config)
        self.m: Weights = {}
        self.v: Weights = {}
        self.trainable: set[str] = set()  # the shared parameters (bind)

    def bind(self, shared: list[str], parameters: set[str]) -> None:
        self.trainable = parameters & set(shared)

    def server_update(self, global_weights: Weights, mean: Weights) -> Weights:
        b1, b2 = self.settings.betas
        eta, tau = self.settings.lr, self.settings.tau
        out = {}
        for key, avg in mean.items():
            if key not in self.trainable:
                out[key] = avg
                continue
            delta = avg - global_weights[key]
            m = self.m.get(key, torch.zeros_like(delta)).mul_(b1).add_(delta, alpha=1 - b1)
            v = (
                self.v.get(key, torch.zeros_like(delta))
                .mul_(b2)
                .addcmul_(delta, delta, value=1 - b2)
            )
            self.m[key], self.v[key] = m, v
            out[key] = global_weights[key] + eta * m / (v.sqrt() + tau)
        return out

    def state_dict(self) -> dict:
        return {"m": dict(self.m), "v": dict(self.v)}

    def load_state_dict(self, state: dict) -> None:
        self.m, self.v = dict(state["m"]), dict(state["v"])
