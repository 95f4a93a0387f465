"""FedOpt (Reddi et al. 2021, Algorithm 2): an adaptive server optimiser on the mean update,
as FedAdam, FedYogi or FedAdagrad (``federated.opt.variant``).

With x the global weights and Delta = mean(client weights) - x:
m <- b1 m + (1 - b1) Delta, then the second moment v by the variant:

* adam:    v <- b2 v + (1 - b2) Delta^2
* yogi:    v <- v - (1 - b2) Delta^2 sign(v - Delta^2)
* adagrad: v <- v + Delta^2

and x <- x + eta m / (sqrt(v) + tau) (no bias correction, as published). The first moment
starts at 0 and the second at tau^2 (the paper's ``v_-1 >= tau^2``);
``federated.opt.v0=zero`` starts it at 0, fedlgr's earlier form, kept to reproduce runs
made with it: its first server step is larger (docs/methods.md). Trainable parameters take
the step; BatchNorm running statistics, which are not parameters, are averaged as in
FedAvg. The paper's reference code never runs this server step; here it does.
"""

from __future__ import annotations

import torch

from fedlgr.core.strategies.base import ServerOptimizer, Weights


def second_moment(variant: str, v: torch.Tensor, delta: torch.Tensor, b2: float) -> torch.Tensor:
    """The next second moment of ``variant`` (Reddi et al., Algorithm 2), in place on ``v``."""
    square = delta * delta
    if variant == "adam":
        return v.mul_(b2).add_(square, alpha=1 - b2)
    if variant == "yogi":
        return v.sub_((1 - b2) * square * torch.sign(v - square))
    return v.add_(square)  # adagrad


class FedOpt(ServerOptimizer):
    def __init__(self, config):
        super().__init__(config)
        self.m: Weights = {}
        self.v: Weights = {}

    def step(self, key: str, weight: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        s = self.settings
        (b1, b2), eta, tau = s.betas, s.lr, s.tau
        m = self.m.get(key, torch.zeros_like(delta)).mul_(b1).add_(delta, alpha=1 - b1)
        start = tau**2 if s.v0 == "tau2" else 0.0
        v = self.v.get(key, torch.full_like(delta, start))
        v = second_moment(s.variant, v, delta, b2)
        self.m[key], self.v[key] = m, v
        return weight + eta * m / (v.sqrt() + tau)

    def state_dict(self) -> dict:
        return {"m": dict(self.m), "v": dict(self.v)}

    def load_state_dict(self, state: dict) -> None:
        self.m, self.v = dict(state["m"]), dict(state["v"])
