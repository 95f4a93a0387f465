"""FedMedian (Yin et al. 2018): the coordinate-wise median of the clients' tensors.

Each coordinate of the new global tensors is the median of that coordinate over the
round's uploads, unweighted - a client's sample count buys it nothing, as the paper's
estimator has it - and with an even number of uploads the mean of the two middle values
(numpy's median, which Flower's FedMedian takes; ``torch.median`` would take the lower
one). It withstands fewer than half of the clients sending arbitrary tensors.
"""

from __future__ import annotations

from fedlgr.core.messages import Weights
from fedlgr.core.server.aggregate import middle, stacked
from fedlgr.core.strategies.base import Strategy


class FedMedian(Strategy):
    needs_uploads = True
    scores_statistic = "median"

    def combine(self, uploads: list[tuple[int, Weights]]) -> Weights:
        n = len(uploads)
        # the middle one (n odd) or the mean of the middle two (n even)
        return {k: middle(stacked(uploads, k), (n - 1) // 2) for k in uploads[0][1]}
