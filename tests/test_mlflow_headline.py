"""What MLflow's UI shows first of a run with system metrics (issue 39, point 2): the
headline scores before ``system/*``, per-round curves of them, only the settings the run
uses as params, and reports that still compare runs by their settings."""

from __future__ import annotations

import time

import mlflow
import pytest

from fedlgr.shell.config import flatten, load_config
from fedlgr.shell.report.cells import check_cells, settings
from fedlgr.shell.report.runs import ReportError, RunRecord
from fedlgr.shell.tracking.context import NOT_PARAMS, run_params
from fedlgr.shell.tracking.experiments import view_state
from fedlgr.shell.tracking.mlflow_run import Tracker
from tests.support.chromium import CHROMIUM, rendered
from tests.support.runs import FAST, fast_config

SCORES = {"test/rmse": 0.81, "test/pcc": 0.53, "test/ccc": 0.45, "test/loss": 0.66}


def test_a_fedavg_run_logs_only_the_settings_it_uses(synth_dir):
    base = [f"data.path={synth_dir}"]
    fedavg = run_params(load_config(FAST, [*base, "method=FedAvg"]))
    assert "federated.strategy" in fedavg and "train.lr_top" in fedavg
    unused = ("federated.prox.", "federated.opt.", "continual.", "federated.dp.", "deploy.")
    assert not [k for k in fedavg if k.startswith(unused)]
    prox = run_params(load_config(FAST, [*base, "method=FedProx", "federated.dp.clip=0.5"]))
    assert prox["federated.prox.mu"] == "0.01" and prox["federated.dp.clip"] == "0.5"
    assert not [k for k in prox if k.startswith(("federated.opt.", "continual.", "deploy."))]
    ewc = ["method=FedRoot-EWC", "continual.tasks=[circle,arrow]"]
    fcl = run_params(load_config(FAST, [*base, *ewc]))
    assert "continual.ewc.lambda_" in fcl and "continual.tasks" in fcl
    assert not [k for k in fcl if k.startswith(("continual.lgr.", "continual.si."))]
    assert "deploy.roster" in run_params(load_config(FAST, base), flower=True)


def _record(params: dict[str, str], run: str) -> RunRecord:
    tags = {"method": "FedProx", "benchmark": "FL", "clients": "2", "augmentation": "false"}
    return RunRecord(run, "1", tags, {"test/rmse": 0.8}, params)


def test_a_report_averages_seeds_logged_either_way_and_refuses_other_used_settings(synth_dir):
    def config(*overrides):
        return load_config(FAST, [f"data.path={synth_dir}", "method=FedProx", *overrides])

    # as fedlgr logged runs before: every setting but the machine's paths
    old = {k: v for k, v in flatten(config("seed=1")).items() if k not in NOT_PARAMS}
    new = run_params(config("seed=2"))
    assert len(new) < len(old) and settings(_record(old, "a")) == settings(_record(new, "b"))
    check_cells([_record(old, "a"), _record(new, "b")], "experiment `x`")  # two seeds
    for other in ("federated.prox.mu=0.1", "federated.dp.clip=0.5"):
        mixed = [_record(new, "b"), _record(run_params(config(other)), "c")]
        with pytest.raises(ReportError, match=other.split("=")[0].replace(".", r"\.")):
            check_cells(mixed, "experiment `x`")


@pytest.mark.slow
def test_system_samples_wait_for_the_first_scores(synth_dir, cache_dir, store):
    """MLflow lists a run's metrics in the order their keys were first written: a sample
    taken before round 1 ends is written after its scores."""
    config = fast_config(synth_dir, cache_dir, store, "tracking.system_metrics_s=1")
    tracker = Tracker(config)
    time.sleep(2.5)  # two samples taken (one a second), held
    client = mlflow.MlflowClient(store)
    assert client.get_run(tracker.run_id).data.metrics == {}
    tracker.log_round(1, {**SCORES, "cost/cpu_s": 1.0, "round/seconds": 2.0})
    tracker.finish()
    keys = [m.key for m in client.get_run(tracker.run_id).data._metric_objs]
    assert keys[:4] == ["test/rmse", "test/pcc", "test/ccc", "test/loss"], keys
    assert "system/cpu_utilization_percentage" in keys  # written, after the scores


def test_the_shared_view_draws_the_headline_on_fitted_axes():
    state = view_state(["method"], [])
    cards = {c["uuid"]: c for c in state["compareRunCharts"]}
    assert [c["type"] for c in state["compareRunCharts"]] == ["LINE"] * 3 + ["SCATTER", "PARALLEL"]
    assert cards["fedlgr-rmse"]["metricKey"] == "test/rmse"
    assert cards["fedlgr-rmse"]["xAxisKey"] == "step"  # a curve over the rounds
    assert cards["fedlgr-scatter"]["xaxis"]["key"] == "test/rmse"
    assert cards["fedlgr-scatter"]["yaxis"]["key"] == "test/pcc"
    headline = ["test/rmse", "test/pcc", "test/ccc"]
    assert [c["metricKey"] for c in state["compareRunCharts"][:3]] == headline
    assert cards["fedlgr-parallel"]["selectedMetrics"] == headline
    assert state["columnOrder"][:3] == [f"metrics.`{m}`" for m in headline]
    assert (state["orderByKey"], state["orderByAsc"]) == ("metrics.`test/rmse`", True)
    assert state["columnWidths"]["metrics.`test/rmse`"] >= 150  # 0.8100731 uncut


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium here (.ci/run installs Debian's)")
@pytest.mark.slow
def test_a_run_page_with_system_metrics_opens_on_the_headline(
    mlflow_server, synth_dir, cache_dir, tmp_path
):
    config = fast_config(
        synth_dir,
        cache_dir,
        mlflow_server,
        "tracking.experiment=ui-system",
        "tracking.system_metrics_s=1",
    )
    tracker = Tracker(config)
    time.sleep(1.5)  # a system sample taken before the first round's scores
    for round_ in (1, 2):
        tracker.log_round(round_, {**SCORES, "cost/cpu_s": 1.0, "round/seconds": 2.0})
    summary = "client    loss   RMSE   PCC\nmean      0.66   0.81   0.53"
    tracker.describe("FedAvg after 2 rounds", summary, {**SCORES, "mean/cost/cpu_s": 1.0})
    tracker.finish()
    client = mlflow.MlflowClient(mlflow_server)
    assert any(k.startswith("system/") for k in client.get_run(tracker.run_id).data.metrics)
    base = f"{mlflow_server}/#/experiments/{tracker.experiment_id}"
    # The run page: its description's headline table, then the metrics table.
    page = rendered(f"{base}/runs/{tracker.run_id}", tmp_path / "run")
    system = page.index(">system/")
    for key in ("test/rmse", "test/pcc", "test/ccc", "mean/cost/cpu_s"):
        assert page.index(f">{key}<") < system, key
