"""What a robot puts into SecAgg+'s masked sum (``deploy.secagg``) and how the server reads the sum
back: one float64 vector per robot (:func:`layout`). Flower's SecAgg+ weighs every robot 1, so a
robot's weight travels inside the vector: its update pre-multiplied, or clipped under DP."""

from __future__ import annotations

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


def robot_vector(res: TrainRes, start: Weights, settings: Mapping) -> tuple[np.ndarray, int]:
    """A robot's float64 vector for its upload ``res`` trained from the global tensors ``start``
    (``settings``: the message's :data:`RECORD`; ``clip`` > 0 under DP), and how many of its values
    SecAgg+ will clip to ``clipping_range``."""
    update = {f"w/{k}": res.weights[k].double() - start[k].double() for k in start}
    update |= {f"p/{k}": v.double() for k, v in res.payload.items()}
    bound = float(settings["clip"])
    if bound > 0:  # DP: clipped here, as the server would (it cannot: it sees the sum)
        update, size = clip(update, bound)
        update[WEIGHT] = torch.tensor(1.0, dtype=torch.float64)
        update[UNCLIPPED] = torch.tensor(centred_bit(size, bound), dtype=torch.float64)
    else:
        weight = float(res.n_samples) / int(settings["max_samples"])
        update = {k: v * weight if k.startswith("w/") else v for k, v in update.items()}
        update[WEIGHT] = torch.tensor(weight, dtype=torch.float64)
    parts = layout(start, res.payload, bound > 0)
    vector = np.concatenate([update[k].cpu().numpy().reshape(-1) for k, _ in parts])
    outside = int(np.count_nonzero(np.abs(vector) > float(settings["clipping_range"])))
    return vector.astype(np.float64), outside


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


def encode_secure_res(
    res: TrainRes, ins: TrainIns, settings: Mapping, evaluated: EvaluateRes | None = None
) -> RecordDict:
    """A robot's SecAgg+ train reply before ``secaggplus_mod`` masks it: its update from the global
    tensors sent with ``ins`` (always, in such a round) as a legacy ``FitRes`` (weight 1) and, in
    the clear, its client, its figures but :data:`HIDDEN` and the previous round's scores."""
    if ins.weights is None:
        raise FedlgrError("a SecAgg+ train message without the global tensors: refused")
    vector, outside = robot_vector(res, ins.weights, settings)
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
