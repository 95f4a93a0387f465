"""FedAvgM (Hsu et al. 2019, "Measuring the effects of non-identical data distribution for
federated visual classification"): FedAvg with server momentum.

With x the global weights and Delta = mean(client weights) - x (the negative of the
paper's pseudo-gradient): v <- momentum v + Delta;  x <- x + lr v. With momentum 0 and
lr 1 this is FedAvg. Trainable parameters take the momentum step; BatchNorm running
statistics, which are not parameters, are averaged as in FedAvg (as FedOpt does here).
"""

from __future__ import annotations

import torch

from fedlgr.core.messages import Weights
from fedlgr.core.strategies.base import ServerOptimizer


class FedAvgM(ServerOptimizer):
    def __init__(self, config):
        super().__init__(config)
        self.velocity: Weights = {}

    def step(self, key: str, weight: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        v = self.velocity.get(key, torch.zeros_like(delta)).mul_(self.settings.momentum)
        self.velocity[key] = v.add_(delta)
        return weight + self.settings.lr * v

    def state_dict(self) -> dict:
        return {"velocity": dict(self.velocity)}

    def load_state_dict(self, state: dict) -> None:
        self.velocity = dict(state["velocity"])
