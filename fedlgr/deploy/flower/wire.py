"""fedlgr's round messages (:mod:`fedlgr.federated.messages`) as Flower ``RecordDict``s.

Tensors travel as Flower ``Array``s holding their raw bytes (``stype`` ``fedlgr.raw``,
little-endian, C order): a message's tensor payload is exactly ``numel x element size``
per tensor, so the bytes measured on the wire are what ``cost/bytes_up`` and
``cost/bytes_down`` report. (Flower's own ``numpy.ndarray`` encoding adds a .npy header of
about 128 bytes per tensor.) Numbers travel in ``ConfigRecord``s; the run's resolved
config goes with every message, so a robot needs nothing from the server's machine.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from flwr.app import Array, ArrayRecord, ConfigRecord, RecordDict

from fedlgr.federated.messages import (
    EvaluateIns,
    EvaluateRes,
    RoundPlan,
    TrainIns,
    TrainRes,
    Weights,
)
from fedlgr.tracking.resources import Usage

RAW = "fedlgr.raw"


def weights_record(weights: Weights) -> ArrayRecord:
    arrays = {}
    for key, tensor in weights.items():
        data = tensor.detach().cpu().contiguous().numpy()
        arrays[key] = Array(
            dtype=str(data.dtype), shape=tuple(data.shape), stype=RAW, data=data.tobytes()
        )
    return ArrayRecord(arrays)


def record_weights(record: ArrayRecord, device: torch.device | str = "cpu") -> Weights:
    out = {}
    for key, array in record.items():
        if array.stype != RAW:
            raise ValueError(f"tensor {key}: unexpected encoding {array.stype!r}")
        data = np.frombuffer(array.data, dtype=np.dtype(array.dtype)).reshape(array.shape)
        out[key] = torch.from_numpy(data.copy()).to(device)
    return out


def payload_bytes(content: RecordDict) -> int:
    """Bytes of tensor data in a message: what the robot's link carries for the model."""
    return sum(len(a.data) for record in content.array_records.values() for a in record.values())


def _plan_record(plan: RoundPlan, config_yaml: str) -> ConfigRecord:
    return ConfigRecord(
        {
            "round": plan.round,
            "task": plan.task,
            "first_of_task": plan.first_of_task,
            "last_of_task": plan.last_of_task,
            "config": config_yaml,
        }
    )


def _plan(content: RecordDict) -> tuple[RoundPlan, str]:
    p = content.config_records["plan"]
    plan = RoundPlan(
        int(p["round"]), int(p["task"]), bool(p["first_of_task"]), bool(p["last_of_task"])
    )
    return plan, str(p["config"])


def _usage_record(usage: Usage | None) -> ConfigRecord:
    if usage is None:
        return ConfigRecord({"present": False})
    return ConfigRecord(
        {
            "present": True,
            "cpu_s": usage.cpu_s,
            "wall_s": usage.wall_s,
            "gpu_util": math.nan if usage.gpu_util is None else float(usage.gpu_util),
            "gpu_mem_mb": math.nan if usage.gpu_mem_mb is None else float(usage.gpu_mem_mb),
        }
    )


def _usage(record: ConfigRecord) -> Usage | None:
    if not record["present"]:
        return None
    gpu, mem = float(record["gpu_util"]), float(record["gpu_mem_mb"])
    return Usage(
        float(record["cpu_s"]),
        float(record["wall_s"]),
        None if math.isnan(gpu) else gpu,
        None if math.isnan(mem) else mem,
    )


# ---------------------------------------------------------------------- train


def encode_train_ins(ins: TrainIns, config_yaml: str) -> RecordDict:
    content = RecordDict({"plan": _plan_record(ins.plan, config_yaml)})
    if ins.weights is not None:
        content["global"] = weights_record(ins.weights)
    return content


def decode_train_ins(content: RecordDict) -> tuple[TrainIns, str]:
    plan, config_yaml = _plan(content)
    weights = record_weights(content["global"]) if "global" in content else None
    return TrainIns(plan, weights), config_yaml


def encode_train_res(res: TrainRes) -> RecordDict:
    report = ConfigRecord(
        {
            "client": res.client,
            "n_samples": res.n_samples,
            "samples": res.samples,
            "loss": float(res.loss),
        }
    )
    return RecordDict(
        {"shared": weights_record(res.weights), "report": report, "usage": _usage_record(res.usage)}
    )


def decode_train_res(content: RecordDict, device: torch.device | str = "cpu") -> TrainRes:
    r = content.config_records["report"]
    return TrainRes(
        int(r["client"]),
        record_weights(content["shared"], device),
        int(r["n_samples"]),
        int(r["samples"]),
        float(r["loss"]),
        _usage(content.config_records["usage"]) or Usage(),
    )


# ---------------------------------------------------------------------- evaluate


def encode_evaluate_ins(ins: EvaluateIns, config_yaml: str) -> RecordDict:
    return RecordDict(
        {"plan": _plan_record(ins.plan, config_yaml), "global": weights_record(ins.weights)}
    )


def decode_evaluate_ins(content: RecordDict) -> tuple[EvaluateIns, str]:
    plan, config_yaml = _plan(content)
    return EvaluateIns(plan, record_weights(content["global"])), config_yaml


def encode_evaluate_res(res: EvaluateRes) -> RecordDict:
    report = ConfigRecord({"client": res.client, "scores": [float(s) for s in res.scores]})
    figures = ConfigRecord({k: float(v) for k, v in res.figures.items()})
    return RecordDict({"report": report, "figures": figures, "usage": _usage_record(res.usage)})


def decode_evaluate_res(content: RecordDict) -> EvaluateRes:
    r = content.config_records["report"]
    figures = {k: float(v) for k, v in content.config_records["figures"].items()}
    scores = [float(s) for s in r["scores"]]
    return EvaluateRes(int(r["client"]), scores, figures, _usage(content.config_records["usage"]))
