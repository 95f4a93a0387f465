"""What a robot puts into SecAgg+'s masked sum (``deploy.secagg``) and how the server reads the sum
back: one float64 vector per robot (:func:`layout`). Flower's SecAgg+ weighs every robot 1, so a
robot's weight travels inside the vector: its update pre-multiplied, or clipped under DP. Each
robot clips its update to a bound (:func:`robot_vector`), so the server can refuse a sum that no
honest robots could have sent (:func:`over_bound`)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import flwr.compat.common.recorddict_compat as compat
import numpy as np
import torch
from flwr.app import ConfigRecord, RecordDict
from flwr.common import Code, FitRes, Status, ndarrays_to_parameters

from fedlgr.core.messages import EvaluateRes, TrainIns, TrainRes, Weights
from fedlgr.core.privacy import UNCLIPPED, centred_bit, clip
from fedlgr.errors import FedlgrError
from fedlgr.shell.deploy.flower import wire

WEIGHT = "secagg/weight"  # the robot's n / max_samples (1 under DP)
RECORD = "fedlgr.secagg"  # the train message's SecAgg settings (a ConfigRecord)
HIDDEN = ("train/samples",)  # figures a robot keeps to itself: its count is in the sum


def layout(shared: Mapping[str, torch.Tensor], payload: Mapping[str, torch.Tensor], dp: bool):
    """(key, shape) of each part of the vector, in its order."""
    parts = [(f"w/{k}", tuple(t.shape)) for k, t in shared.items()]
    parts += [(f"p/{k}", tuple(payload[k].shape)) for k in sorted(payload)]
    parts.append((WEIGHT, ()))
    if dp:
        parts.append((UNCLIPPED, ()))
    return parts


def message_settings(secagg, clip: float) -> dict[str, float | int]:
    """The SecAgg settings a train message carries (:data:`RECORD`) from ``deploy.secagg``;
    ``clip``: the round's DP clip norm (0: no DP)."""
    return {
        "clip": float(clip),
        "norm_bound": float(secagg.norm_bound),
        "max_samples": int(secagg.max_samples),
        "clipping_range": float(secagg.clipping_range),
    }


def robot_vector(res: TrainRes, start: Weights, settings: Mapping) -> tuple[np.ndarray, int, float]:
    """A robot's float64 vector for its upload ``res`` trained from the global tensors ``start``
    (``settings``: the message's :data:`RECORD`), how many of its values SecAgg+ will clip to
    ``clipping_range``, and its update's norm before it is clipped here - to DP's clip norm
    (``clip`` > 0), else to ``norm_bound`` - as one vector with its payload (as the server would
    clip or screen it: it cannot, it sees the sum)."""
    update = {f"w/{k}": res.weights[k].double() - start[k].double() for k in start}
    update |= {f"p/{k}": v.double() for k, v in res.payload.items()}
    dp = float(settings["clip"]) > 0
    bound = float(settings["clip"] if dp else settings["norm_bound"])
    update, size = clip(update, bound)
    if dp:
        update[WEIGHT] = torch.tensor(1.0, dtype=torch.float64)
        update[UNCLIPPED] = torch.tensor(centred_bit(size, bound), dtype=torch.float64)
    else:
        weight = float(res.n_samples) / int(settings["max_samples"])
        update = {k: v * weight if k.startswith("w/") else v for k, v in update.items()}
        update[WEIGHT] = torch.tensor(weight, dtype=torch.float64)
    parts = layout(start, res.payload, dp)
    vector = np.concatenate([update[k].cpu().numpy().reshape(-1) for k, _ in parts])
    outside = int(np.count_nonzero(np.abs(vector) > float(settings["clipping_range"])))
    return vector.astype(np.float64), outside, size


def split(vector: np.ndarray, parts: list[tuple[str, tuple[int, ...]]]) -> Weights:
    """The vector's parts by key (float64 tensors); a length that is not the layout's is
    refused."""
    size = sum(int(np.prod(shape)) for _, shape in parts)
    if vector.size != size:
        raise ValueError(f"a SecAgg+ sum of {vector.size} values, the layout has {size}")
    out, at = {}, 0
    for key, shape in parts:
        count = int(np.prod(shape))
        out[key] = torch.from_numpy(vector[at : at + count].reshape(shape).copy()).double()
        at += count
    return out


def error_bound(secagg, robots: int, total: float, dp: bool) -> float:
    """The most one coordinate of the released mean update can be off from the plain mean (none
    clipped): each robot's value is rounded to a step of ``2 c / Q``, so the sum is off by under
    ``robots x 2c/Q`` - the bound under DP, divided by ``total / W`` without."""
    step = 2 * secagg.clipping_range / secagg.quantization_range
    if dp:
        return robots * step
    return robots * step * secagg.max_samples / total


def over_bound(found: Weights, robots: int, total: float, secagg, clip: float) -> str | None:
    """Why ``found`` - the sum of ``robots`` vectors, split (:func:`split`), its weight taken out,
    ``total`` the summed sample count (the robots under DP) - is no sum of honest robots' vectors,
    or None. Honest robots clip their update and payload as one vector to a bound B
    (:func:`robot_vector`); SecAgg+'s clipping to [-c, c] only shrinks a value and its rounding
    moves each value of the sum by under ``robots x 2c/Q``, ``robots x 2c/Q x sqrt(values)`` in
    norm. So, up to that, the sum's updates and payloads have a norm of at most ``robots x clip``
    under DP; without, its weighted updates at most ``B x total / max_samples`` (its mean update,
    what the global model moves by, at most B) and its payloads at most ``robots x B``, B being
    ``norm_bound``. (Float64's rounding over the sum is ~1e-11 of it, far below that slack.)"""
    level = robots * 2 * secagg.clipping_range / secagg.quantization_range

    def norm(prefixes: tuple[str, ...]) -> tuple[float, float]:
        """The norm of the sum's parts that start with ``prefixes``, and its slack."""
        parts = [v for k, v in found.items() if k.startswith(prefixes)]
        values = sum(v.numel() for v in parts)
        return math.sqrt(sum(float(v.pow(2).sum()) for v in parts)), level * math.sqrt(values)

    if clip > 0:
        size, slack = norm(("w/", "p/"))
        if size > robots * clip + slack:
            return (
                f"its updates' norm {size:.4g} is over {robots} robots x the clip norm "
                f"{clip:.4g} (+{slack:.2g} for quantisation)"
            )
        return None
    bound = secagg.norm_bound
    size, slack = norm(("w/",))
    weight = total / secagg.max_samples  # the sum of the robots' n / max_samples
    if size > bound * weight + slack:
        return (
            f"its mean update's norm {size / weight:.4g} is over deploy.secagg.norm_bound="
            f"{bound:g} (+{slack / weight:.2g} for quantisation)"
        )
    size, slack = norm(("p/",))
    if size > robots * bound + slack:
        return (
            f"its payloads' norm {size:.4g} is over {robots} robots x deploy.secagg.norm_bound="
            f"{bound:g} (+{slack:.2g} for quantisation)"
        )
    return None


def encode_secure_res(
    res: TrainRes, ins: TrainIns, settings: Mapping, evaluated: EvaluateRes | None = None
) -> RecordDict:
    """A robot's SecAgg+ train reply before ``secaggplus_mod`` masks it: its update from the global
    tensors sent with ``ins`` (always, in such a round) as a legacy ``FitRes`` (weight 1) and, in
    the clear, its client, its figures but :data:`HIDDEN` and the previous round's scores."""
    if ins.weights is None:
        raise FedlgrError("a SecAgg+ train message without the global tensors: refused")
    vector, outside, size = robot_vector(res, ins.weights, settings)
    bound = float(settings["norm_bound"])
    if float(settings["clip"]) == 0 and size > bound:
        print(
            f"round {ins.plan.round}: the update's norm {size:.4g} is over deploy.secagg."
            f"norm_bound={bound:g}: clipped to it",
            flush=True,
        )
    if outside:
        print(
            f"round {ins.plan.round}: {outside} values outside deploy.secagg.clipping_range="
            f"{float(settings['clipping_range']):g} are clipped by SecAgg+",
            flush=True,
        )
    fit = FitRes(Status(Code.OK, ""), ndarrays_to_parameters([vector]), 1, {})
    content = compat.fitres_to_recorddict(fit, keep_input=False)
    content["report"] = ConfigRecord({"client": res.client})
    clear = {k: v for k, v in res.figures.items() if k not in HIDDEN}
    content["figures"] = ConfigRecord(clear)
    wire.put_evaluated(content, evaluated)
    return content
