"""FedBN (Li et al. 2021): BatchNorm parameters and running statistics stay local."""

from __future__ import annotations

from fedlgr.core.strategies.base import Strategy


class FedBN(Strategy):
    def shares(self, key: str, batchnorm: bool) -> bool:
        return not batchnorm
