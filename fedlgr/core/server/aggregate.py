"""The server's arithmetic: sample-weighted sums and means of client tensors.

Sums are taken in float64 so that the order in which clients (or processes) contribute
changes nothing visible; the in-process runtime across Fabric's processes adds the
per-process sums with one ``all_reduce`` before dividing.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

from fedlgr.core.messages import Weights


def weighted_sum(uploads: Iterable[tuple[int, Weights]], keys: list[str]) -> tuple[Weights, float]:
    """Sum of ``n * weights`` over the uploads, and the sum of ``n``."""
    sums: Weights = {}
    total = 0.0
    for n, weights in uploads:
        for k in keys:
            term = n * weights[k].detach().double()
            sums[k] = term if k not in sums else sums[k] + term
        total += n
    return sums, total


def weighted_mean(
    uploads: Iterable[tuple[int, Weights]], keys: list[str], like: Weights | None = None
) -> Weights:
    """Sample-weighted mean (FedAvg), in the dtypes of ``like`` (default: float32)."""
    sums, total = weighted_sum(uploads, keys)
    return finish_mean(sums, total, like)


def finish_mean(sums: Weights, total: float, like: Weights | None = None) -> Weights:
    if total <= 0:
        raise ValueError("no samples to aggregate")
    return {k: (s / total).to(like[k].dtype if like else torch.float32) for k, s in sums.items()}


def stacked(uploads: list[tuple[int, Weights]], key: str) -> torch.Tensor:
    """Tensor ``key`` of every upload, stacked along a new first dimension (float64)."""
    return torch.stack([weights[key].detach().double() for _, weights in uploads])


def middle(values: torch.Tensor, cut: int) -> torch.Tensor:
    """Per coordinate, the mean of ``values`` (stacked along dimension 0) once the ``cut``
    smallest and ``cut`` largest are left out."""
    n = len(values)
    return values.sort(dim=0).values[cut : n - cut].mean(dim=0)
