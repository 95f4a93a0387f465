"""What the server takes of an upload.

A client's upload must hold exactly the tensors the server shares with it, each of the
global tensor's shape and dtype and every value finite, and a sample count that is a
positive whole number no larger than the client's training scenes of the task where the
server knows them (the in-process runtime holds the split; the Flower runtime, the
roster's ``scenes``); what its strategy's plugins send beside them (SCAFFOLD's
control-variate change) is held to the same checks, and no BatchNorm variance may be below
0. An upload whose update - its tensors minus the global ones, and its plugins' change - is
over ``federated.norm_ratio`` times the median of the round's other updates is refused too
(any update at all, where the others did not move). A refused upload reaches nothing: the
round aggregates the others, and its record names the client and why.

What a client reports - its training figures with its upload, its scores - is checked
where the client is not in the server's process (the Flower runtime): each figure must
have its column in the round's record and be a finite number in its range - a score's
bounds (errors not below 0, correlations in [-1, 1]; :class:`~fedlgr.core.metrics.Score`),
a cost not below 0 (:func:`figures_refusal`). Where the server scores the very model a
client scores - the whole model shared (FedAvg's scope), ``federated.server_eval`` on - its
scores must be the server's own (:func:`claim_refusal`).
"""

from __future__ import annotations

import hashlib
import math
import statistics
from collections.abc import Collection, Mapping

import torch

from fedlgr.core import metrics
from fedlgr.core.messages import TrainRes, Weights

MAX_COUNT = 2**53  # a sample count above this is no float's whole number: a weight of nothing


def refusal(
    result: TrainRes, shared: Weights, capacity: int | None = None, payload: Weights | None = None
) -> str | None:
    """Why ``result`` cannot be aggregated with the global tensors ``shared``, or None;
    ``payload``: zeros shaped like what the strategy's plugins send beside them (their
    keys exactly, of those shapes and dtypes, finite)."""
    sent = result.weights if isinstance(result.weights, dict) else {}
    why = _keys_refusal(sent, shared, "shared tensor(s)", "tensor(s) that are not shared")
    if why is not None:
        return why
    n = result.n_samples
    if isinstance(n, bool) or not isinstance(n, int) or n <= 0:
        return f"sample count {n!r} is not a positive whole number"
    if n > MAX_COUNT:
        return f"sample count of {n.bit_length()} bits is beyond any dataset (over 2^53)"
    if capacity is not None and n > capacity:
        return f"sample count {n} exceeds its {capacity} training scenes"
    extra = result.payload if isinstance(result.payload, dict) else None
    like = payload or {}
    if extra is None:
        return "its payload is not a set of tensors"
    why = _keys_refusal(
        extra, like, "payload tensor(s)", "payload tensor(s) this strategy does not use"
    )
    if why is not None:
        return why
    tensors = sent | extra  # every key checked present above
    for key, expected in (*shared.items(), *like.items()):
        why = _tensor_refusal(key, tensors[key], expected)
        if why is not None:
            return why
    return None


def _keys_refusal(sent: dict, like: Weights, what: str, unknown: str) -> str | None:
    missing = [k for k in like if k not in sent]
    extra = sorted(str(k) for k in sent if k not in like)
    if missing:
        return f"{len(missing)} {what} missing ({missing[0]}, ...)"
    if extra:
        return f"{len(extra)} {unknown} ({extra[0][:80]}, ...)"
    return None


def _tensor_refusal(key: str, tensor, like: torch.Tensor) -> str | None:
    """Why ``tensor`` cannot stand for ``like``: not a dense tensor of values, another shape
    or dtype, values that are not finite, a variance below 0."""
    if not isinstance(tensor, torch.Tensor):
        return f"{key} is not a tensor"
    if tensor.layout != torch.strided or tensor.device.type == "meta":
        return f"{key} is not a dense tensor of values ({tensor.layout}, {tensor.device.type})"
    if tensor.shape != like.shape:
        return f"{key} has shape {list(tensor.shape)}, not {list(like.shape)}"
    if tensor.dtype != like.dtype:
        return f"{key} is {str(tensor.dtype).removeprefix('torch.')}, not " + str(
            like.dtype
        ).removeprefix("torch.")
    if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
        return f"{key} holds values that are not finite"
    if key.endswith("running_var") and bool((tensor < 0).any()):
        return f"{key} holds variances below 0"
    return None


def update_norm(result: TrainRes, shared: Weights) -> float:
    """The Euclidean norm of the upload's change of the global floating-point tensors."""
    total = 0.0
    for key, like in shared.items():
        if like.is_floating_point():
            total += float((result.weights[key].double() - like.double()).pow(2).sum())
    return math.sqrt(total)


def payload_norm(result: TrainRes) -> float:
    """The Euclidean norm of what the upload's plugins send (a change too: SCAFFOLD's
    control variate's), screened apart from the tensors' change: a payload x8 hides in the
    sum of two norms where the tensors' change is the larger."""
    total = sum(
        float(t.double().pow(2).sum()) for t in result.payload.values() if t.is_floating_point()
    )
    return math.sqrt(total)


def digest(result: TrainRes) -> str:
    """A fingerprint of the upload - its tensors, payload and sample count - to know a replay
    of an earlier one (BLAKE2b of their bytes, in key order)."""
    hashed = hashlib.blake2b(digest_size=16)
    hashed.update(str(result.n_samples).encode())
    for part in (result.weights, result.payload):
        for key in sorted(part):
            hashed.update(key.encode())
            hashed.update(
                part[key]
                .detach()
                .cpu()
                .contiguous()
                .reshape(-1)
                .view(torch.uint8)
                .numpy()
                .tobytes()
            )
    return hashed.hexdigest()


def oversized(norms: dict[int, float], ratio: float, what: str = "update") -> dict[int, str]:
    """The clients whose update norm is over ``ratio`` times the median of the others'
    (every other accepted upload of the round: a client is not its own yardstick, so two
    uploads can be compared), with why; where the others did not move at all, any update
    is. None where ``ratio`` is 0 or an upload has no other to be compared with."""
    if not ratio or len(norms) < 2:
        return {}
    out = {}
    for client, norm in sorted(norms.items()):
        others = statistics.median(v for c, v in norms.items() if c != client)
        if others <= 0 and norm > 0:
            out[client] = f"{what} norm {norm:.3g} where the round's others did not move"
        elif others > 0 and norm > ratio * others:
            out[client] = (
                f"{what} norm {norm:.3g} is over {ratio:g} x the others' median {others:.3g}"
            )
    return out


def capped_counts(counts: Mapping[int, int], ratio: float) -> dict[int, int]:
    """The clients whose sample count is over ``ratio`` times the median of the round's other
    counts, each with that cap (a whole number, at least 1): a weighted mean trusts the
    counts it weighs by, and a client is not its own yardstick. None where ``ratio`` is 0 or
    a count has no other to be compared with."""
    if not ratio or len(counts) < 2:
        return {}
    out = {}
    for client, n in sorted(counts.items()):
        cap = max(
            1, math.floor(ratio * statistics.median(v for c, v in counts.items() if c != client))
        )
        if n > cap:
            out[client] = cap
    return out


# Figures outside the scores (metrics.SCORES) with a range of their own, by name.
OTHER_BOUNDS = {"recon_mse": metrics.ERROR}  # LGR's generator error
# float32 sums can put a perfect correlation a hair over 1: a bound is widened by this
# fraction of itself (an error, a sum of squares, never drops below 0)
SLACK = 1e-5


def _bounds() -> dict[str, tuple[float, float]]:
    """The range of every bounded figure by the names its keys carry: a score's
    (``test/pcc``, ``task/circle/pcc``) and its per-action figure's (``test/mse/vacuum``)."""
    out = dict(OTHER_BOUNDS)
    for score in metrics.SCORES:
        out[score.name] = out[score.per_action] = score.bounds
    return out


def figures_refusal(figures: Mapping, keys: Collection[str]) -> str | None:
    """Why a client's reported ``figures`` cannot be recorded in a round whose columns are
    ``keys``, or None."""
    bounds = _bounds()
    for key, value in figures.items():
        if key not in keys:
            return f"{str(key)[:80]!r} is not a figure of this run"
        if isinstance(value, bool) or not isinstance(value, int | float):
            return f"{key} = {str(value)[:40]!r} is not a number"
        try:
            value = float(value)
        except OverflowError:
            return f"{key} = an integer of {value.bit_length()} bits, beyond any float"
        if not math.isfinite(value):
            return f"{key} = {value} is not finite"
        ranges = [bounds[p] for p in key.split("/") if p in bounds]
        if key.startswith("cost/"):
            ranges.append(metrics.ERROR)
        for low, high in ranges:
            if not low - SLACK * abs(low) <= value <= high + SLACK * abs(high):
                shown = f"below {low:g}" if high == math.inf else f"out of [{low:g}, {high:g}]"
                return f"{key} = {value:.4g} is {shown}"
    return None


# A robot's score of the global model may differ from the server's own evaluation of it by
# float rounding (another CPU's kernels: ~1e-7 measured), never by this much, relative to
# max(1, |score|).
CLAIM_TOLERANCE = 1e-4


def claim_refusal(figures: Mapping, served: Mapping) -> str | None:
    """Why a client's scores of the global model disagree with the server's own evaluation of
    the same model on the same scenes (``served``: its ``server/test/*``, ``server/task/*``),
    or None; only where the client's model is the global one (the whole model shared)."""
    for key, value in figures.items():
        own = served.get(f"server/{key}")
        if own is None or not str(key).startswith(("test/", "task/")):
            continue
        if abs(float(value) - own) > CLAIM_TOLERANCE * max(1.0, abs(own)):
            return (
                f"{key} = {float(value):.4g} where the server's own evaluation of the same "
                f"model gives {own:.4g}"
            )
    return None
