"""Aggregation strategies (``federated.strategy``), one module each, registered in
:data:`fedlgr.core.methods.STRATEGIES`. A strategy has a server half (which tensors are
exchanged, the server update) and a client half (plugins in local training, e.g.
FedProx's proximal term), so this package sits beside ``client/`` and ``server/``."""

from __future__ import annotations

from typing import TYPE_CHECKING

from fedlgr.core.methods import STRATEGIES
from fedlgr.core.strategies.base import FedAvg, Strategy

if TYPE_CHECKING:
    from fedlgr.core.settings import FederatedConfig


def build_strategy(config: FederatedConfig) -> Strategy:
    """The strategy ``federated.strategy`` names, with its settings."""
    return STRATEGIES[config.strategy].load()(config)


__all__ = ["FedAvg", "Strategy", "build_strategy"]
