"""FedAvgM (Hsu et al. 2019, "Measuring the effects of non-identical data distribution for
federated visual classification"): FedAvg with server momentum.

With x the global weights and Delta = mean(client weights) - x (the negative of the
paper's pseudo-gradient): v <- momentum v + Delta;  x <- x + lr v. With momentum 0 and
lr 1 this is FedAvg. Trainable parameters take the momentum step; BatchNorm running
statistics, which are not parameters, are averaged as in FedAvg (as FedOpt does here).
"""

from __future__ import annotations

import torch

from fedlgr.federated.messages import Weights
from fedlgr.federated.strategies.base import Strategy


class FedAvgM(Strategy):
    def __init__(self, config):
        super().__init__(config)
        self.velocity: Weights = {}
        self.trainable: set[str] = set()  # the shared parameters (bind)

    def bind(self, shared: list[str], parameters: set[str]) -> None:
        self.trainable = parameters & set(shared)

    def server_update(self, global_weights: Weights, mean: Weights) -> Weights:
        beta, lr = self.settings.momentum, self.settings.lr
        out = {}
        for key, avg in mean.items():
            if key not in self.trainable:
                out[key] = avg
                continue
            delta = avg - global_weights[key]
            v = self.velocity.get(key, torch.zeros_like(delta)).mul_(beta).add_(delta)
            self.velocity[key] = v
            out[key] = global_weights[key] + lr * v
        return out

    def state_dict(self) -> dict:
        return {"velocity": dict(self.velocity)}

    def load_state_dict(self, state: dict) -> None:
        self.velocity = dict(state["velocity"])
