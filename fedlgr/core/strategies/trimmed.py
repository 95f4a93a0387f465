"""FedTrimmedAvg (Yin et al. 2018): the coordinate-wise beta-trimmed mean.

For each coordinate, the largest and the smallest ``floor(beta n)`` of the round's ``n``
uploads are left out and the rest averaged, unweighted (the paper's estimator; Flower's
FedTrimmedAvg cuts the same, as scipy's ``trim_mean``). ``federated.trimmed.beta``
(0 <= beta < 0.5, default 0.2) is the fraction of clients assumed faulty at either end;
beta 0 is the plain mean of the uploads.
"""

from __future__ import annotations

from fedlgr.core.messages import Weights
from fedlgr.core.server.aggregate import middle, stacked
from fedlgr.core.strategies.base import Strategy


class FedTrimmedAvg(Strategy):
    needs_uploads = True

    @property
    def scores_statistic(self) -> str:
        return f"trimmed {self.settings.beta:g}"  # the uploads' cut, on the scores

    def combine(self, uploads: list[tuple[int, Weights]]) -> Weights:
        cut = int(self.settings.beta * len(uploads))
        return {k: middle(stacked(uploads, k), cut) for k in uploads[0][1]}
