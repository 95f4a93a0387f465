"""The client/server boundary: what may cross it, how the server records a round with a
robot missing, and the Flower wire format (tensor payload = the cost figures)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fedlgr.core.messages import (
    EvaluateIns,
    EvaluateRes,
    RoundPlan,
    TrainIns,
    TrainRes,
    check_shared,
    nbytes,
)
from fedlgr.core.meters.costs import Usage
from fedlgr.core.metrics import SCORES
from fedlgr.core.server.side import ServerSide
from fedlgr.errors import FedlgrError
from fedlgr.shell.config import load_config
from fedlgr.shell.deploy.flower import wire
from tests.support.runs import FAST


def trained_figures(samples: int, loss: float, usage: Usage) -> dict[str, float]:
    """What a client's training reports, by name."""
    return {"train/loss": loss, "train/samples": float(samples), **usage.figures()}


@pytest.fixture
def config(synth_dir, cache_dir):
    return load_config(
        FAST, [f"data.path={synth_dir}", "method=FedRootAvg", "tracking.enabled=false"]
    )


def test_nothing_but_the_shared_tensors_may_cross(config, synth_dir):
    from fedlgr.core.client.side import ClientSide
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.data.splits import make_split

    scenes = load_scenes(config.data)
    side = ClientSide(
        config, scenes, make_split(scenes.table, config.data), [1], torch.device("cpu")
    )
    assert all(k.startswith("root.") for k in side.keys)  # FedRoot: the root only
    [res] = side.train(TrainIns(RoundPlan(1, 0, True, True)))
    first = next(iter(res.weights))
    with pytest.raises(FedlgrError, match=rf"x: .*missing: \['{first}'\]"):
        check_shared({k: v for k, v in res.weights.items() if k != first}, side.keys, "x", "root.")
    assert set(res.weights) == set(side.keys) and res.client == 1
    side.keys = [*side.keys, "top.net.1.weight"]  # a scope that would let the top out ...
    with pytest.raises(FedlgrError, match=r"client 1's upload: \['top.net.1.weight'\] outside"):
        side.upload(side.clients[0])  # ... is refused: the client uploads the root only
    top = {"top.net.1.weight": torch.zeros(2)}
    side.keys = side.keys[:-1]
    with pytest.raises(FedlgrError, match=r"server's download: \['top.net.1.weight'\] outside"):
        side.evaluate(EvaluateIns(RoundPlan(1), {**res.weights, **top}))
    server = ServerSide(config)
    before = {k: v.clone() for k, v in server.global_weights.items()}
    server.aggregate([TrainRes(1, {**res.weights, **top}, 10)])  # refused, the round goes on
    assert "tensor(s) that are not shared (top.net.1.weight, ...)" in server.refused[1]
    assert all(torch.equal(v, before[k]) for k, v in server.global_weights.items())


def test_a_round_with_a_robot_missing_has_its_row_nan_and_names_it(config):
    server = ServerSide(config)
    scores = {k: 0.5 for k in server.round_keys if k.startswith(("test/", "task/"))}
    trained = TrainRes(0, {}, 12, trained_figures(24, 0.25, Usage(1.5, 2.0, None, None)))
    row = server.row(trained, EvaluateRes(0, scores), bytes_up=100, bytes_down=300)
    log = server.round_log(RoundPlan(2), server.table({0: row}), 3.0, missing=(1,))
    assert log.column("bytes_up").tolist()[0] == 100 and log.column("cpu_s")[0] == 1.5
    assert np.isnan(log.table[1]).all()
    assert log.mean("test_loss") == 0.5  # the mean of the robots that reported
    metrics = log.metrics()
    assert metrics["round/missing_clients"] == 1.0
    assert "test/client0/loss" in metrics and "test/client1/loss" not in metrics
    assert [r["test_loss"] for r in log.rows()] == [0.5, None]


def test_the_summary_averages_a_robot_s_costs_over_the_rounds_it_took_part_in(config):
    """One missed round leaves the robot's CPU, upload and the mean row as numbers (they
    were nan), averaged over what was measured."""
    from fedlgr.shell.run.result import ExperimentResult

    server = ServerSide(config)
    scores = {k: 0.5 for k in server.round_keys if k.startswith(("test/", "task/"))}
    result = ExperimentResult(config)
    for round_, present in ((1, (0, 1)), (2, (0,)), (3, (0, 1))):
        rows = {}
        for c in present:
            usage = Usage(1.0 + c + round_, 2.0, None, None)
            trained = TrainRes(c, {}, 12, trained_figures(24, 0.25, usage))
            rows[c] = server.row(trained, EvaluateRes(c, scores), 1000 * (c + 1), 300)
        missing = tuple(c for c in (0, 1) if c not in present)
        result.rounds.append(server.round_log(RoundPlan(round_), server.table(rows), 1.0, missing))
    table = result.summary()
    assert "nan" not in table
    # client  loss  RMSE  PCC  ...  CPU s/round  wall s/round  upload/round: a column per
    # score, then the costs
    cells = {line[:8].strip(): line[8:].split() for line in table.splitlines()[2:] if line.strip()}
    at = len(SCORES)
    cpu = {name: float(row[at]) for name, row in cells.items()}
    assert cells["client 1"][at + 2 : at + 4] == ["2.0", "KiB"]  # its upload, rounds 1 and 3
    assert cpu["client 0"] == (2 + 3 + 4) / 3  # rounds 1-3
    assert cpu["client 1"] == (3 + 5) / 2  # rounds 1 and 3: round 2 is missing
    assert cpu["mean"] == (2 + 3 + 4 + 3 + 5) / 5


def test_the_wire_carries_tensors_as_their_raw_bytes():
    weights = {
        "root.w": torch.randn(3, 4),
        "root.bn.running_var": torch.rand(5, dtype=torch.float64),
        "root.half": torch.randn(2, 2).half(),
    }
    res = TrainRes(1, weights, 10, trained_figures(20, 0.5, Usage(1.0, 2.0, 30.0, None)))
    content = wire.encode_train_res(res)
    assert wire.payload_bytes(content) == nbytes(weights) == 48 + 40 + 8
    # one Flower Array for all the tensors: Flower moves each Array as an object of its
    # own (an HTTP request each way)
    assert [len(r) for r in content.array_records.values()] == [1]
    back = wire.decode_train_res(content)
    assert all(
        torch.equal(back.weights[k], v) and back.weights[k].dtype == v.dtype
        for k, v in weights.items()
    )
    figures = back.figures
    assert (back.client, back.n_samples, figures["train/samples"], figures["train/loss"]) == (
        1,
        10,
        20,
        0.5,
    )
    assert figures == {**res.figures, "cost/gpu_util": 30.0} and "cost/gpu_mem_mb" not in figures

    ins, evaluate, text = wire.decode_train_ins(
        wire.encode_train_ins(TrainIns(RoundPlan(3, 1, True, False)), "seed: 1")
    )
    assert ins == TrainIns(RoundPlan(3, 1, True, False), None) and text == "seed: 1"
    assert evaluate is None
    ins, _ = wire.decode_evaluate_ins(
        wire.encode_evaluate_ins(EvaluateIns(RoundPlan(3), weights), "x")
    )
    assert list(ins.weights) == list(weights)

    evaluated = EvaluateRes(0, {"test/loss": 1.0, "test/rmse": math.nan, "lgr/fd_latent": 2.5})
    back = wire.decode_evaluate_res(wire.encode_evaluate_res(evaluated))
    assert back.figures["test/loss"] == 1.0 and math.isnan(back.figures["test/rmse"])
    assert back.figures["lgr/fd_latent"] == 2.5 and len(back.figures) == 3


def test_one_message_carries_a_round_s_evaluation_and_the_next_round_s_training():
    """deploy.evaluate=with_next_round: the new global tensors travel once, for the
    evaluation of round 2 and the training of round 3; the reply carries both results."""
    weights = {"root.w": torch.randn(3, 4), "root.b": torch.randn(4)}
    content = wire.encode_train_ins(
        TrainIns(RoundPlan(3, 1, True, False)),
        "seed: 1",
        EvaluateIns(RoundPlan(2, 0, False, True), weights),
    )
    assert wire.payload_bytes(content) == nbytes(weights)  # the tensors once
    ins, evaluate, text = wire.decode_train_ins(content)
    assert ins == TrainIns(RoundPlan(3, 1, True, False), None) and text == "seed: 1"
    assert evaluate.plan == RoundPlan(2, 0, False, True)
    assert all(torch.equal(evaluate.weights[k], v) for k, v in weights.items())
    with pytest.raises(ValueError, match="one set of tensors"):
        wire.encode_train_ins(
            TrainIns(RoundPlan(3), weights), "", EvaluateIns(RoundPlan(2), weights)
        )

    trained = TrainRes(1, weights, 10, trained_figures(20, 0.5, Usage(1.0, 2.0, None, None)))
    task_end = Usage(3.0, 4.0, None, None).figures()
    evaluated = EvaluateRes(
        1, {"test/loss": 0.25, "test/rmse": 0.5, "lgr/fd_latent": 2.5, **task_end}
    )
    reply = wire.encode_train_res(trained, evaluated)
    assert wire.payload_bytes(reply) == nbytes(weights)
    assert wire.decode_train_res(reply).n_samples == 10
    assert wire.decode_evaluated(reply) == evaluated
    assert wire.decode_evaluated(wire.encode_train_res(trained)) is None
