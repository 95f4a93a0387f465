"""fedlgr's round messages (:mod:`fedlgr.core.messages`) as Flower ``RecordDict``s: tensors packed
in one ``Array`` (:func:`put_weights`), so the bytes on the wire are what ``cost/bytes_*`` report;
numbers by name in ``ConfigRecord``s; the resolved config with every message."""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import torch
from flwr.app import Array, ArrayRecord, ConfigRecord, RecordDict

from fedlgr.core.messages import (
    EvaluateIns,
    EvaluateRes,
    RoundPlan,
    TrainIns,
    TrainRes,
    Weights,
)
from fedlgr.core.metrics import Figures
from fedlgr.errors import FedlgrError

PACKED = "fedlgr.packed"
# What decoding a malformed message raises: a record or field missing, a value of the
# wrong type, tensor bytes that do not match their index.
MALFORMED = (KeyError, ValueError, TypeError, AttributeError, IndexError, OverflowError)


def put_weights(content: RecordDict, name: str, weights: Weights) -> None:
    """``weights`` into ``content`` as one Flower ``Array`` (``name``: the raw bytes, little-endian,
    C order, one after another) and its index (``name.index``). One array, not one per tensor:
    Flower moves each ``Array`` in HTTP requests of its own."""
    keys, dtypes, ndims, dims, parts = [], [], [], [], []
    for key, tensor in weights.items():
        data = tensor.detach().cpu().contiguous().numpy()
        keys.append(key)
        dtypes.append(data.dtype.newbyteorder("<").str)
        ndims.append(data.ndim)
        dims.extend(int(d) for d in data.shape)
        parts.append(data.astype(data.dtype.newbyteorder("<"), copy=False).tobytes())
    blob = b"".join(parts)
    array = Array(dtype="uint8", shape=(len(blob),), stype=PACKED, data=blob)
    content[name] = ArrayRecord({"tensors": array})
    content[f"{name}.index"] = ConfigRecord(
        {"keys": keys, "dtypes": dtypes, "ndims": ndims, "dims": dims}
    )


def get_weights(content: RecordDict, name: str, device: torch.device | str = "cpu") -> Weights:
    array = content.array_records[name]["tensors"]
    if array.stype != PACKED:
        raise ValueError(f"{name}: unexpected encoding {array.stype!r}")
    index = content.config_records[f"{name}.index"]
    out, offset, at = {}, 0, 0
    dims = list(index["dims"])
    for key, dtype, ndim in zip(index["keys"], index["dtypes"], index["ndims"], strict=True):
        shape = tuple(dims[at : at + int(ndim)])
        at += int(ndim)
        kind = np.dtype(dtype)
        count = math.prod(shape)
        data = np.frombuffer(array.data, dtype=kind, count=count, offset=offset)
        offset += count * kind.itemsize
        out[key] = torch.from_numpy(data.reshape(shape).astype(kind.newbyteorder("="))).to(device)
    if offset != len(array.data):
        raise ValueError(f"{name}: {len(array.data)} bytes for tensors of {offset}")
    return out


def payload_bytes(content: RecordDict) -> int:
    """Bytes of tensor data in a message: what the robot's link carries for the model."""
    return sum(len(a.data) for record in content.array_records.values() for a in record.values())


def train_payload_bytes(content: RecordDict) -> int:
    """Bytes of the strategy's payload a train message carries (0: none)."""
    return sum(len(a.data) for a in content.array_records.get("payload", {}).values())


def _plan_record(
    plan: RoundPlan, config_yaml: str | None = None, client: int | None = None
) -> ConfigRecord:
    record = dataclasses.asdict(plan)
    if config_yaml is not None:
        record["config"] = config_yaml
    if client is not None:
        record["client"] = int(client)
    return ConfigRecord(record)


def _round_plan(p: ConfigRecord) -> RoundPlan:
    return RoundPlan(
        int(p["round"]), int(p["task"]), bool(p["first_of_task"]), bool(p["last_of_task"])
    )


def _figures(record: ConfigRecord) -> Figures:
    """Figures by key (scores, costs, plugins' figures), each a number."""
    return {str(k): float(v) for k, v in record.items()}


def _payload(content: RecordDict) -> Weights:
    return get_weights(content, "payload") if "payload" in content.array_records else {}


# ---------------------------------------------------------------------- train


def slot(content: RecordDict) -> int | None:
    """The client slot the server gives the robot (from the roster; None: the robot's
    own ``--client``, a run without a roster)."""
    plan = content.config_records["plan"]
    return int(plan["client"]) if "client" in plan else None


RUN_KEY = re.compile(r"[A-Za-z0-9_-]{1,64}")  # an MLflow run id (32 hex digits), a Flower one


def run_key(content: RecordDict) -> str:
    """The run the robot keeps its state under ("": the Flower run's). It names a folder on the
    robot, so anything but a run id is refused: a server must not choose where a robot writes."""
    key = str(content.config_records["plan"].get("run", ""))
    if key and not RUN_KEY.fullmatch(key):
        raise FedlgrError(
            f"the server's run key {key[:80]!r} is not a run id (1 to 64 letters, digits, - "
            "or _): refused, nothing written"
        )
    return key


def stamp_run(content: RecordDict, run: str) -> RecordDict:
    """Name the run (its MLflow id) in a message: a resumed run is a new Flower run."""
    if run:
        content.config_records["plan"]["run"] = run
    return content


def encode_train_ins(
    ins: TrainIns,
    config_yaml: str,
    evaluate: EvaluateIns | None = None,
    client: int | None = None,
) -> RecordDict:
    """The round's training; with ``evaluate``, first the previous round's evaluation of
    its global tensors (which the robot then trains on: ``ins.weights`` must be None);
    ``client``: the robot's slot."""
    content = RecordDict({"plan": _plan_record(ins.plan, config_yaml, client)})
    if ins.payload:
        put_weights(content, "payload", ins.payload)
    if evaluate is not None:
        if ins.weights is not None:
            raise ValueError("a train message with an evaluation carries one set of tensors")
        content["evaluate"] = _plan_record(evaluate.plan)
        put_weights(content, "global", evaluate.weights)
    elif ins.weights is not None:
        put_weights(content, "global", ins.weights)
    return content


def decode_train_ins(content: RecordDict) -> tuple[TrainIns, EvaluateIns | None, str]:
    plan = content.config_records["plan"]
    weights = get_weights(content, "global") if "global" in content else None
    ins = TrainIns(_round_plan(plan), weights, _payload(content))
    if "evaluate" not in content:
        return ins, None, str(plan["config"])
    evaluate = EvaluateIns(_round_plan(content.config_records["evaluate"]), weights)
    return dataclasses.replace(ins, weights=None), evaluate, str(plan["config"])


def encode_train_res(res: TrainRes, evaluated: EvaluateRes | None = None) -> RecordDict:
    report = ConfigRecord({"client": res.client, "n_samples": res.n_samples})
    content = RecordDict({"report": report, "figures": ConfigRecord(dict(res.figures))})
    put_weights(content, "shared", res.weights)
    if res.payload:
        put_weights(content, "payload", res.payload)
    put_evaluated(content, evaluated)
    return content


def put_evaluated(content: RecordDict, evaluated: EvaluateRes | None) -> None:
    """The previous round's scores, where a train reply carries them."""
    if evaluated is not None:
        for name, record in encode_evaluate_res(evaluated, "evaluated.").items():
            content[name] = record


def decode_train_res(content: RecordDict, device: torch.device | str = "cpu") -> TrainRes:
    """A robot's upload; its sample count as sent (the server's checks refuse one that is
    not a positive whole number: 2.5 is not rounded to 2)."""
    r = content.config_records["report"]
    return TrainRes(
        int(r["client"]),
        get_weights(content, "shared", device),
        r["n_samples"],
        _figures(content.config_records["figures"]),
        _payload(content),
    )


def decode_evaluated(content: RecordDict) -> EvaluateRes | None:
    """The previous round's scores a train reply carries (None: it carries none)."""
    return decode_evaluate_res(content, "evaluated.") if "evaluated.report" in content else None


# ---------------------------------------------------------------------- evaluate


def encode_evaluate_ins(
    ins: EvaluateIns, config_yaml: str, client: int | None = None
) -> RecordDict:
    content = RecordDict({"plan": _plan_record(ins.plan, config_yaml, client)})
    put_weights(content, "global", ins.weights)
    return content


def decode_evaluate_ins(content: RecordDict) -> tuple[EvaluateIns, str]:
    plan = content.config_records["plan"]
    return EvaluateIns(_round_plan(plan), get_weights(content, "global")), str(plan["config"])


def encode_evaluate_res(res: EvaluateRes, prefix: str = "") -> RecordDict:
    return RecordDict(
        {
            f"{prefix}report": ConfigRecord({"client": res.client}),
            f"{prefix}figures": ConfigRecord(dict(res.figures)),
        }
    )


def decode_evaluate_res(content: RecordDict, prefix: str = "") -> EvaluateRes:
    records = content.config_records
    client = int(records[f"{prefix}report"]["client"])
    return EvaluateRes(client, _figures(records[f"{prefix}figures"]))
