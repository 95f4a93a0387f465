"""The aggregation strategy interface, and FedAvg (McMahan et al. 2017).

A strategy says which of the scope's tensors are exchanged (``shares``), what each client
adds to its local training (``client_plugins``) and how the server turns the clients'
sample-weighted mean into the next global weights (``server_update``). What is shared at
all - the whole model or the root only - is the orthogonal *scope*
(``fedlgr.federated.scope``): FedRoot x {Avg, BN, Prox, Opt, Distill} are combinations,
not ten classes. Subclasses override only what differs (Flower's ``Strategy``).
"""

from __future__ import annotations

import torch

from fedlgr.config import FederatedConfig
from fedlgr.federated.plugins import ClientPlugin

Weights = dict[str, torch.Tensor]


class Strategy:
    """FedAvg: every tensor in scope is shared; the new global is the mean of the
    clients' tensors weighted by their number of training samples."""

    name = "Avg"

    def __init__(self, config: FederatedConfig):
        self.config = config

    def shares(self, key: str, batchnorm: bool) -> bool:
        """Is this in-scope tensor exchanged? ``batchnorm``: it belongs to a BatchNorm layer."""
        return True

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
