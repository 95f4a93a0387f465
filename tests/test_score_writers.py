"""A score is declared once (fedlgr.core.metrics.SCORES, its per-action function in
fedlgr.core.meters.scores.PER_ACTION) and reaches every writer: the meter, results.csv's
columns, the server's screen of a robot's report, the MLflow view, each run's curves.png
and summary, the forgetting demo's table, a sweep's objective check, the report's tables,
plots and a sweep's trials. A made-up score, the hit rate, is added as a researcher would
add one, and each writer is asked for it by name."""

from __future__ import annotations

import csv
import json
import re
import sys

import mlflow
import numpy as np
import pytest
import torch
from mlflow.entities import Metric

from fedlgr.core import metrics
from fedlgr.core.meters.scores import PER_ACTION, regression_scores
from fedlgr.core.metrics import Score, column, round_keys
from fedlgr.core.records import RoundLog
from fedlgr.core.server.screen import figures_refusal
from fedlgr.errors import ConfigError
from fedlgr.shell.cli.demo import forgetting_table
from fedlgr.shell.config import load_config
from fedlgr.shell.report import make_report
from fedlgr.shell.run.result import ExperimentResult
from fedlgr.shell.sweep import load_sweep
from fedlgr.shell.tracking.experiments import view_state
from fedlgr.shell.tracking.mlflow_run import note_keys
from fedlgr.shell.tracking.plots import curves_png
from tests.support.figures import drawn_figures
from tests.support.runs import FAST

HIT = Score("hit", "Hit", True, "hit", "share of outputs within 0.5 of the rating", (0.0, 1.0))


def _hit(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return ((pred - target).abs() < 0.5).double().mean(dim=0)


@pytest.fixture
def hit(monkeypatch) -> Score:
    """HIT in SCORES - in every module that imported the tuple, as if it had been declared
    there - and its per-action function in the meter's table."""
    declared = metrics.SCORES
    scores = (*declared, HIT)
    for module in list(sys.modules.values()):
        for name, value in list(vars(module).items()) if module is not None else ():
            if value is declared:
                monkeypatch.setattr(module, name, scores)
    monkeypatch.setitem(PER_ACTION, "hit", _hit)
    return HIT


def test_the_meter_and_the_csv_columns_carry_a_new_score(hit):
    # two scenes: errors 0.1 and 1.0 on the first action (one hit of two), 0.1 and 0.3 on
    # the seven others (two of two): a hit rate of (0.5 + 7 x 1) / 8
    target = torch.arange(16.0).reshape(2, 8)
    pred = target + torch.tensor([[0.1] * 8, [1.0] + [0.3] * 7])
    figures = regression_scores(pred, target).figures("test", per_action=True)
    assert figures["test/hit"] == pytest.approx(7.5 / 8)
    assert figures["test/hit/vacuum"] == pytest.approx(0.5)
    assert figures["test/hit/mop"] == pytest.approx(1.0)
    keys = round_keys(["all"])
    assert "test/hit" in keys and "test/hit/vacuum" in keys


def test_the_screen_holds_a_robots_new_score_to_its_bounds(hit):
    keys = {"test/hit", "test/hit/vacuum", "task/circle/hit"}
    assert figures_refusal({"test/hit": 1.0, "task/circle/hit": 0.0}, keys) is None
    assert figures_refusal({"test/hit": 1.5}, keys) == "test/hit = 1.5 is out of [0, 1]"
    assert figures_refusal({"test/hit/vacuum": -0.2}, keys) == (
        "test/hit/vacuum = -0.2 is out of [0, 1]"
    )


def test_the_mlflow_view_shows_a_new_headline_score(hit):
    state = view_state(["method"], [])
    cards = {c["uuid"]: c for c in state["compareRunCharts"]}
    assert cards["fedlgr-hit"]["type"] == "LINE" and cards["fedlgr-hit"]["metricKey"] == "test/hit"
    assert "test/hit" in cards["fedlgr-parallel"]["selectedMetrics"]
    assert "metrics.`test/hit`" in state["selectedColumns"]
    # the scatter stays the first error against the first correlation
    assert cards["fedlgr-scatter"]["xaxis"]["key"] == "test/rmse"
    assert cards["fedlgr-scatter"]["yaxis"]["key"] == "test/pcc"


def _curves_panels(title: str) -> list[str]:
    """The y labels of a 2-round, 2-client run's curves.png, in panel order."""
    scores = [column(f"test/{s.name}") for s in metrics.SCORES]
    rows = [{"round": k, "client": c, **dict.fromkeys(scores, 0.5)} for k in (1, 2) for c in (0, 1)]
    with drawn_figures() as drawn:
        assert curves_png(rows, title)[:4] == b"\x89PNG"
    return drawn[title]


def test_a_runs_curves_draw_every_headline_score():
    assert _curves_panels("FedAvg-2c") == ["test RMSE", "test PCC", "test CCC"]


def test_a_runs_curves_draw_a_new_score(hit):
    assert _curves_panels("FedAvg-2c") == ["test RMSE", "test PCC", "test CCC", "test Hit"]


def _fcl_result() -> ExperimentResult:
    """An FCL run of 2 clients, circle then arrow, one round each: every figure 0.5, after
    each task every score 0.5, circle's forgetting after arrow 0.1."""
    config = load_config(FAST, ["method=FedAvg-EWC", "data.path=/x", "tracking.enabled=false"])
    tasks = list(config.continual.tasks)
    keys = round_keys(tasks)
    result = ExperimentResult(config)
    for k, task in enumerate(tasks, start=1):
        result.rounds.append(RoundLog(k, task, keys, np.full((2, len(keys)), 0.5), 1.0))
    names = [s.name for s in metrics.SCORES]
    for k in (1, 2):
        after = {f"after_task{k}/test/{n}": 0.5 for n in names}
        after |= {f"after_task{k}/task/{t}/{n}": 0.5 for t in tasks[:k] for n in names}
        result.after_tasks.append(after)
    result.after_tasks[1] |= {f"after_task2/forgetting/circle/{n}": 0.1 for n in names}
    return result


def _headers(text: str) -> list[str]:
    """A console table's headings (cells are 2 spaces apart; a heading holds single ones)."""
    return re.split(r"  +", text.splitlines()[0].strip())


def test_the_run_summary_shows_a_new_score_and_its_forgetting(hit):
    summary = _fcl_result().summary()
    assert _headers(summary)[:6] == ["client", "loss", "RMSE", "PCC", "CCC", "Hit"]
    tasks = summary[summary.index("task  ") :]
    assert _headers(tasks) == [
        "task",
        "tested on",
        "loss",
        "RMSE",
        "PCC",
        "CCC",
        "Hit",
        "forgetting",
    ]
    assert "circle: RMSE +0.100 PCC +0.100 CCC +0.100 Hit +0.100" in tasks


def test_the_forgetting_demo_has_a_column_per_headline_score(hit):
    text = forgetting_table([_fcl_result()])
    assert _headers(text) == [
        "method",
        *("circle RMSE T1", "PCC T1", "CCC T1", "Hit T1"),
        *("circle RMSE T2", "PCC T2", "CCC T2", "Hit T2"),
        *("forgot RMSE", "forgot PCC", "forgot CCC", "forgot Hit"),
        *("arrow RMSE T2", "PCC T2", "CCC T2", "Hit T2"),
    ]
    assert text.splitlines()[2].split()[1:] == ["0.500"] * 8 + ["0.100"] * 4 + ["0.500"] * 4


def test_a_sweeps_objective_check_names_a_new_score(hit, tmp_path):
    path = tmp_path / "hits.yaml"
    path.write_text(f"base: {FAST}\nobjective: {{metric: test/hti}}\nspace:\n  seed: [0]\n")
    with pytest.raises(ConfigError) as refused:
        load_sweep(path)
    assert "they log e.g. test/ccc, test/hit, test/pcc, test/rmse, mean/cost/cpu_s" in str(
        refused.value
    )


def test_a_runs_description_opens_with_a_new_headline_score(hit):
    assert note_keys()[:4] == ["test/rmse", "test/pcc", "test/ccc", "test/hit"]


def _finished_run(client, experiment_id: str, tags: dict, figures: dict) -> str:
    """A run logging each figure at rounds 1 and 2 (the second value last)."""
    run_id = client.create_run(experiment_id, tags=tags).info.run_id
    logged = [
        Metric(k, v + 0.01 * (2 - step), 0, step) for step in (1, 2) for k, v in figures.items()
    ]
    client.log_batch(run_id, metrics=logged)  # one write per run
    client.set_terminated(run_id, "FINISHED")
    return run_id


@pytest.mark.slow  # a new MLflow store and matplotlib's first figures: seconds
def test_a_sweeps_report_tables_plots_and_trials_carry_a_new_score(hit, store, tmp_path):
    """An FCL sweep of two trials, each logging every score (the new one too) per round,
    after each task, and Task 1's forgetting."""
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("new-score", artifact_location=tmp_path.as_uri())
    tags = {"method": "FedAvg-EWC", "benchmark": "FCL", "clients": "2", "augmentation": "false"}
    sweep = {"sweep": "hits", "objective": "minimize test/rmse"}
    parent = _finished_run(client, experiment_id, {**tags, **sweep, "fedlgr.kind": "sweep"}, {})
    for trial, value in enumerate((0.4, 0.6)):
        swept = json.dumps({"continual.ewc.lambda_": 10**trial})
        trial_tags = {**tags, **sweep, "trial": str(trial), "mlflow.parentRunId": parent}
        scores = {s.name: value for s in metrics.SCORES}
        logged = {f"test/{name}": v for name, v in scores.items()}
        for k in (1, 2):
            logged |= {f"after_task{k}/test/{name}": v for name, v in scores.items()}
        logged |= {f"after_task1/task/circle/{name}": v for name, v in scores.items()}
        logged |= {f"after_task2/forgetting/circle/{name}": 0.1 for name in scores}
        _finished_run(client, experiment_id, {**trial_tags, "swept": swept}, logged)

    with drawn_figures() as drawn:
        report = make_report(store, sweep="hits", out=tmp_path / "out", log=False)

    with (tmp_path / "out" / "table2.csv").open(newline="") as f:
        header = next(csv.reader(f))
    assert "2c/after_task1/test/hit" in header and "2c/after_task2/test/hit" in header
    with (tmp_path / "out" / "trials.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["test/hit"]) for r in rows] == [0.4, 0.6]  # best first
    assert "test Hit ▲" in (tmp_path / "out" / "trials.md").read_text(encoding="utf-8")
    assert {"fcl_curves.png", "forgetting.png"} <= set(report.plots)
    assert "test Hit" in drawn["FCL: test scores per round"]
    forgetting = "FCL: forgetting of Task 1 after the last task (positive = forgotten)"
    assert "forgetting of Task 1, Hit" in drawn[forgetting]
