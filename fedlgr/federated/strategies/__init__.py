"""Aggregation strategies by config name (``federated.strategy``)."""

from fedlgr.federated.strategies.base import FedAvg, Strategy
from fedlgr.federated.strategies.fedbn import FedBN
from fedlgr.federated.strategies.feddistill import FedDistill
from fedlgr.federated.strategies.fedopt import FedOpt
from fedlgr.federated.strategies.fedprox import FedProx

STRATEGIES: dict[str, type[Strategy]] = {
    "avg": FedAvg,
    "bn": FedBN,
    "prox": FedProx,
    "opt": FedOpt,
    "distill": FedDistill,
}

__all__ = ["STRATEGIES", "FedAvg", "FedBN", "FedDistill", "FedOpt", "FedProx", "Strategy"]
