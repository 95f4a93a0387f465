"""The aggregation strategy interface, and FedAvg (McMahan et al. 2017).

A strategy says which of the scope's tensors are exchanged (``shares``), what each client
adds to its local training (``client_plugins``) and how the server turns the clients'
sample-weighted mean into the next global weights (``server_update``). What is shared at
all - the whole model or the root only - is the orthogonal *scope*
(``fedlgr.core.scope``): FedRoot x every strategy are combinations, not a class
each. Subclasses override only what differs (Flower's ``Strategy``).
"""

from __future__ import annotations

import torch

from fedlgr.core.client.plugins import ClientPlugin
from fedlgr.core.messages import Weights
from fedlgr.shell.config import FederatedConfig


class Strategy:
    """FedAvg: every tensor in scope is shared; the new global is the mean of the
    clients' tensors weighted by their number of training samples."""

    def __init__(self, config: FederatedConfig):
        self.config = config
        self.settings = config.settings  # federated.<strategy>: FedProx's mu, FedOpt's lr, ...

    def bind(self, shared: list[str], parameters: set[str]) -> None:
        """Called once by the server with the model's shared tensors' names and those that
        are trainable parameters (not BatchNorm statistics): a server optimiser steps the
        parameters only (:class:`ServerOptimizer`)."""

    def shares(self, key: str, batchnorm: bool) -> bool:
        """Is this in-scope tensor exchanged? ``batchnorm``: it belongs to a BatchNorm layer."""
        return True

    # The classes of what ``client_plugins`` returns (the server reads what they measure).
    client_plugin_types: tuple[type[ClientPlugin], ...] = ()

    def client_plugins(self, client: int) -> list[ClientPlugin]:
        """What this strategy adds to a client's local training (one list per client)."""
        return []

    def server_update(self, global_weights: Weights, mean: Weights) -> Weights:
        """The next global weights from the clients' sample-weighted mean."""
        return mean

    def state_dict(self) -> dict:
        """Server-side state (e.g. FedOpt's moments), for checkpoints."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore what ``state_dict`` returned."""


FedAvg = Strategy


class ServerOptimizer(Strategy):
    """A strategy whose server update is an optimiser step on the shared parameters, from
    the clients' mean update Delta = mean - global (FedOpt, FedAvgM); tensors that are not
    parameters (BatchNorm running statistics) take the plain mean, as in FedAvg."""

    def __init__(self, config: FederatedConfig):
        super().__init__(config)
        self.trainable: set[str] = set()  # the shared parameters (bind)

    def bind(self, shared: list[str], parameters: set[str]) -> None:
        self.trainable = parameters & set(shared)

    def server_update(self, global_weights: Weights, mean: Weights) -> Weights:
        return {
            key: self.step(key, global_weights[key], avg - global_weights[key])
            if key in self.trainable
            else avg
            for key, avg in mean.items()
        }

    def step(self, key: str, weight: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        """The next global value of parameter ``key`` from its value and its mean update."""
        raise NotImplementedError
