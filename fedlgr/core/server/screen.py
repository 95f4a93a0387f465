"""What the server takes of an upload.

A client's upload must hold exactly the tensors the server shares with it, each of the
global tensor's shape and dtype and every value finite, and a sample count that is a
positive whole number no larger than the client's training scenes of the task where the
server knows them (in simulation it holds the split). An upload whose update - its tensors
minus the global ones - is over ``federated.norm_ratio`` times the round's median update
norm is refused too. A refused upload reaches nothing: the round aggregates the others,
and its record names the client and why.

What a client reports - its training figures with its upload, its scores - is checked
where the client is not the server's own (a robot): each figure must have its column in
the round's record and be a finite number, errors and costs not below 0, correlations in
[-1, 1] (:func:`figures_refusal`).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Collection, Mapping

import torch

from fedlgr.core.messages import TrainRes, Weights


def refusal(result: TrainRes, shared: Weights, capacity: int | None = None) -> str | None:
    """Why ``result`` cannot be aggregated with the global tensors ``shared``, or None."""
    sent = result.weights if isinstance(result.weights, dict) else {}
    missing = [k for k in shared if k not in sent]
    extra = sorted(k for k in sent if k not in shared)
    if missing:
        return f"{len(missing)} shared tensor(s) missing ({missing[0]}, ...)"
    if extra:
        return f"{len(extra)} tensor(s) that are not shared ({extra[0]}, ...)"
    n = result.n_samples
    if isinstance(n, bool) or not isinstance(n, int) or n <= 0:
        return f"sample count {n!r} is not a positive whole number"
    if capacity is not None and n > capacity:
        return f"sample count {n} exceeds its {capacity} training scenes"
    for key, like in shared.items():
        tensor = sent[key]
        if not isinstance(tensor, torch.Tensor):
            return f"{key} is not a tensor"
        if tensor.shape != like.shape:
            return f"{key} has shape {list(tensor.shape)}, not {list(like.shape)}"
        if tensor.dtype != like.dtype:
            return f"{key} is {str(tensor.dtype).removeprefix('torch.')}, not " + str(
                like.dtype
            ).removeprefix("torch.")
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            return f"{key} holds values that are not finite"
    return None


def update_norm(result: TrainRes, shared: Weights) -> float:
    """The Euclidean norm of the upload's change of the global floating-point tensors."""
    total = 0.0
    for key, like in shared.items():
        if like.is_floating_point():
            total += float((result.weights[key].double() - like.double()).pow(2).sum())
    return math.sqrt(total)


def oversized(norms: dict[int, float], ratio: float) -> dict[int, str]:
    """The clients whose update norm is over ``ratio`` times the median of ``norms`` (of
    every accepted upload of the round), with why; none where ``ratio`` is 0."""
    if not ratio or not norms:
        return {}
    median = statistics.median(norms.values())
    if median <= 0:
        return {}
    return {
        client: f"update norm {norm:.3g} is over {ratio:g} x the round's median {median:.3g}"
        for client, norm in sorted(norms.items())
        if norm > ratio * median
    }


CORRELATIONS = frozenset({"pcc", "ccc"})  # in [-1, 1]
NOT_NEGATIVE = frozenset({"loss", "mse", "rmse", "recon_mse"})  # errors, and every cost
SLACK = 1e-5  # float32 sums can put a perfect correlation a hair over 1


def figures_refusal(figures: Mapping, keys: Collection[str]) -> str | None:
    """Why a client's reported ``figures`` cannot be recorded in a round whose columns are
    ``keys``, or None."""
    for key, value in figures.items():
        if key not in keys:
            return f"{str(key)[:80]!r} is not a figure of this run"
        if isinstance(value, bool) or not isinstance(value, int | float):
            return f"{key} = {str(value)[:40]!r} is not a number"
        if not math.isfinite(value):
            return f"{key} = {value} is not finite"
        parts = set(key.split("/"))
        if parts & CORRELATIONS and not -1 - SLACK <= value <= 1 + SLACK:
            return f"{key} = {value:.4g} is out of [-1, 1]"
        if (parts & NOT_NEGATIVE or key.startswith("cost/")) and value < 0:
            return f"{key} = {value:.4g} is below 0"
    return None
