"""The headline of the clients' scores (issue 50, "scores are evidence, not facts"): the
simulated attackers apart, a refused upload's sender without a score, the robust strategies'
statistic on robots, the spread and the outliers - on hand numbers and in a run."""

from __future__ import annotations

import mlflow
import numpy as np
import pytest

from fedlgr.core.faults import Faults
from fedlgr.core.forgetting import METRICS, ForgettingTracker
from fedlgr.core.records import RoundLog, headline
from fedlgr.core.server.screen import claim_refusal
from fedlgr.core.strategies import build_strategy
from fedlgr.shell.config import load_config
from fedlgr.shell.report.runs import _record
from fedlgr.shell.run.experiment import run_experiment
from tests.support.runs import fast_config

KEYS = ["test/rmse", "test/pcc", "cost/cpu_s"]


def log(rmse, pcc=None, **fields) -> RoundLog:
    """A round of len(rmse) clients: their RMSE, PCC (0.5 each by default) and CPU s (1..n)."""
    n = len(rmse)
    pcc = [0.5] * n if pcc is None else pcc
    table = np.array([rmse, pcc, [float(c + 1) for c in range(n)]], dtype=np.float64).T
    return RoundLog(1, "all", KEYS, table, 1.0, **fields)


def test_the_statistics_by_hand():
    """mean 2.2; median 2; trimmed 0.2 of 5 values cuts 1 at either end: (1+2+3)/3 = 2;
    trimmed 0.2 of 4 values cuts none; NaN is left out; nothing: None."""
    values = np.array([0.0, 1.0, 2.0, 3.0, 5.0])
    assert headline(values) == pytest.approx(2.2)
    assert headline(values, "median") == 2.0
    assert headline(values, "trimmed 0.2") == 2.0
    assert headline(np.array([0.0, 1.0, 2.0, 9.0]), "trimmed 0.2") == 3.0
    assert headline(np.array([1.0, np.nan, 3.0])) == 2.0
    assert headline(np.array([np.nan]), "median") is None


def test_simulated_attackers_are_apart_and_a_refused_upload_scores_nothing():
    """Clients 1 and 3 attack, client 4's upload was refused: the headline RMSE is the mean
    of clients 0 and 2 (0.6), the attackers' mean (1.5) is ``byzantine/test/rmse``; a cost
    stays the mean over every client; per-client values are all logged."""
    round_ = log(
        [0.5, 1.0, 0.7, 2.0, 0.1],
        byzantine=(1, 3),
        refused={4: "upload: update norm 9 is over 2 x the others' median 1", 2: "scores: x"},
    )
    assert round_.counted.tolist() == [True, False, True, False, False]
    metrics = round_.metrics()
    assert metrics["test/rmse"] == pytest.approx(0.6, abs=1e-12)
    assert metrics["byzantine/test/rmse"] == pytest.approx(1.5, abs=1e-12)
    assert metrics["cost/cpu_s"] == pytest.approx(3.0)  # (1+2+3+4+5)/5
    assert metrics["test/client3/rmse"] == 2.0 and metrics["test/client4/rmse"] == 0.1
    # the interquartile range of 0.5 and 0.7 (numpy's linear percentiles: 0.65 - 0.55)
    assert metrics["spread/test/rmse"] == pytest.approx(0.1)
    assert round_.mean("test_rmse") == round_.mean("test/rmse") == pytest.approx(0.6)


def test_robots_scores_take_the_robust_strategys_statistic():
    """FedMedian and Krum: the median; FedTrimmedAvg: its beta-trimmed mean; the others:
    the mean - what ServerSide gives RoundLog where the clients are robots."""
    config = load_config(None, ["federated.strategy=median"]).federated
    assert build_strategy(config).scores_statistic == "median"
    config = load_config(None, ["federated.strategy=krum"]).federated
    assert build_strategy(config).scores_statistic == "median"
    config = load_config(None, ["federated.strategy=trimmed", "federated.trimmed.beta=0.25"])
    assert build_strategy(config.federated).scores_statistic == "trimmed 0.25"
    assert build_strategy(load_config(None, []).federated).scores_statistic == "mean"
    # a liar's 0.010 among three honest robots: the median does not move far
    round_ = log([0.674, 0.660, 0.010, 0.681], statistic="median")
    assert round_.metrics()["test/rmse"] == pytest.approx((0.660 + 0.674) / 2)
    assert log([0.674, 0.660, 0.010, 0.681]).metrics()["test/rmse"] == pytest.approx(0.50625)


def test_a_score_far_from_the_others_is_named_an_outlier():
    """Median 0.674 of (0.674, 0.660, 0.010, 0.681), MAD 0.0105: 0.010 is 63 MADs away and
    named, by the score it is far in; the honest spread is not. Clients scoring one model
    (MAD 0) differ by float rounding only: no outlier; with fewer than 3 clients: none."""
    round_ = log([0.674, 0.660, 0.010, 0.681], [0.6, 0.61, 0.99, 0.62])
    assert round_.outliers() == {2: "RMSE 0.010 (median 0.667)"}
    assert round_.metrics()["round/outliers"] == 1.0
    same = log([0.6740001, 0.674, 0.6740002, 0.674])
    assert same.outliers() == {} and "round/outliers" not in same.metrics()
    assert log([0.674, 0.010]).outliers() == {}
    # a known attacker is not an outlier of the honest clients: it is apart already
    assert log([0.674, 0.660, 0.010, 0.681], byzantine=(2,)).outliers() == {}


def test_forgetting_is_the_honest_clients():
    """Circle's RMSE learnt at (0.5, 0.5, 0.5); later (0.6, 3.0, 0.7) with client 1 an
    attacker: forgetting +0.15 (the mean of +0.1 and +0.2), not +0.93."""
    keys = [f"{p}/{m}" for p in ("test", "task/circle", "task/arrow") for m in METRICS]

    def round_(task, circle):
        table = np.full((3, len(keys)), 0.5)
        table[:, keys.index("task/circle/rmse")] = circle
        return RoundLog(1, task, keys, table, 1.0, byzantine=(1,))

    tracker = ForgettingTracker(["circle", "arrow"])
    tracker.end_of_task(round_("circle", [0.5, 0.5, 0.5]), 0)
    forgot = tracker.forgetting(round_("arrow", [0.6, 3.0, 0.7]))
    assert forgot["forgetting/circle/rmse"] == pytest.approx(0.15)
    assert forgot["forgetting/circle/pcc"] == 0.0


@pytest.mark.slow
def test_fedrootmedian_with_4_poisoners_headlines_the_honest_clients(synth_dir, cache_dir, store):
    """Issue 50's acceptance: FedRootMedian, 10 clients, 4 training on labels of 1: the run's
    ``test/rmse`` is the 6 honest clients' mean to 1e-6, the poisoners' mean is
    ``byzantine/test/rmse``, the console's summary says so, and the report labels the row."""
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        "data.modality=features",
        "data.clients=10",
        "federated.rounds=2",
        "method=FedRootMedian",
        "federated.faults.byzantine=4",
        "federated.faults.attack=labels",
        "federated.faults.label=1",
    )
    bad = Faults(config.federated.faults, 10, config.seed).byzantine
    lines: list[str] = []
    result = run_experiment(config, echo=lines.append)
    run = mlflow.MlflowClient(store).get_run(result.run_id)
    metrics = run.data.metrics
    rmse = result.final.column("test/rmse")  # each client's, as results.csv has them
    honest = [rmse[c] for c in range(10) if c not in bad]
    poisoned = [rmse[c] for c in sorted(bad)]
    assert len(honest) == 6
    assert abs(metrics["test/rmse"] - float(np.mean(honest))) < 1e-6
    assert abs(metrics["byzantine/test/rmse"] - float(np.mean(poisoned))) < 1e-6
    assert min(poisoned) > max(honest)  # what the headline would have mixed in
    said = "\n".join(lines)
    assert f"not the 4 simulated attackers (client {', '.join(map(str, sorted(bad)))}" in said
    assert "byzantine RMSE" in said
    # the report's row for the run (fedlgr report reads it so)
    assert _record(run).method == "FedRootMedian, 4/10 byzantine (labels)"


def test_a_claim_is_held_to_the_servers_own_evaluation_of_the_same_model():
    """The server scored the global model RMSE 0.674, PCC 0.41: a robot claiming 0.010 is
    refused naming both; float rounding (1e-6) passes; a figure the server has no score of
    (a training loss) is not compared."""
    served = {"server/test/rmse": 0.674, "server/test/pcc": 0.41, "cost/server_cpu_s": 1.0}
    assert claim_refusal({"test/rmse": 0.010, "test/pcc": 0.41}, served) == (
        "test/rmse = 0.01 where the server's own evaluation of the same model gives 0.674"
    )
    assert claim_refusal({"test/rmse": 0.674001, "test/pcc": 0.4100004}, served) is None
    assert claim_refusal({"train/loss": 9.0, "test/ccc": 0.9}, served) is None
