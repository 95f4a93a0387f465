"""Krum and Multi-Krum (Blanchard et al. 2017): the uploads closest to their neighbours.

Each of the round's ``n`` uploads is scored by the sum of its squared Euclidean distances
to its ``n - f - 2`` nearest other uploads (over every floating-point tensor shared: with
FedRoot, the root's); Krum (``federated.krum.m`` = 1) takes the best-scored upload as the
new global tensors, Multi-Krum (``m`` > 1) the unweighted mean of the ``m`` best, as
published (Flower's MultiKrum weights them by sample count). ``federated.krum.f`` is the
number of Byzantine clients assumed; the guarantee needs ``n > 2 f + 2`` uploads a round
(fewer are scored over their single nearest neighbour, as Flower does: with 2 clients
Krum keeps client 0's tensors). Ties go to the lower client index.
"""

from __future__ import annotations

import torch

from fedlgr.core.messages import Weights
from fedlgr.core.strategies.base import Strategy


def krum_scores(vectors: torch.Tensor, f: int) -> torch.Tensor:
    """Each row's Krum score: the sum of its squared distances to its ``n - f - 2``
    nearest other rows (at least one)."""
    n = len(vectors)
    distances = torch.zeros(n, n, dtype=torch.float64, device=vectors.device)
    for i in range(n):
        for j in range(i + 1, n):
            distances[i, j] = distances[j, i] = (vectors[i] - vectors[j]).pow(2).sum()
    closest = max(1, n - f - 2)
    others = [torch.cat([row[:i], row[i + 1 :]]) for i, row in enumerate(distances)]
    return torch.stack([row.sort().values[:closest].sum() for row in others])


class Krum(Strategy):
    needs_uploads = True
    scores_statistic = "median"  # Krum's f < n/2 - 1 attackers cannot move it far

    def combine(self, uploads: list[tuple[int, Weights]]) -> Weights:
        keys = list(uploads[0][1])
        floats = [k for k in keys if uploads[0][1][k].is_floating_point()]
        vectors = torch.stack(
            [torch.cat([w[k].detach().double().flatten() for k in floats]) for _, w in uploads]
        )
        scores = krum_scores(vectors, self.settings.f)
        best = torch.argsort(scores, stable=True)[: min(self.settings.m, len(uploads))]
        chosen = [uploads[int(i)][1] for i in best]
        return {k: torch.stack([w[k].detach().double() for w in chosen]).mean(dim=0) for k in keys}
