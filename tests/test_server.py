"""End to end against a real ``mlflow server`` on localhost: ``fedlgr run --tracking-uri``
logs there, and the run reads back through the REST client."""

from __future__ import annotations

import math

import mlflow
import pytest

from fedlgr.shell.cli import main
from tests.support.runs import FAST


@pytest.mark.slow
def test_a_run_against_a_real_mlflow_server_reads_back_through_rest(
    mlflow_server, synth_dir, cache_dir, capsys
):
    code = main(
        [
            "run",
            str(FAST),
            f"data.path={synth_dir}",
            f"data.cache_dir={cache_dir}",
            "method=FedRootAvg",
            "tracking.experiment=server-e2e",
            "--tracking-uri",
            mlflow_server,
        ]
    )
    assert code == 0
    run_id = capsys.readouterr().out.split("MLflow run ")[1].split()[0]

    client = mlflow.MlflowClient(mlflow_server)  # the REST client: an http:// URI
    experiment = client.get_experiment_by_name("server-e2e")
    (run,) = client.search_runs([experiment.experiment_id])
    assert run.info.run_id == run_id and run.info.status == "FINISHED"
    assert run.data.tags["method"] == "FedRootAvg"
    assert run.data.params["federated.scope"] == "root"
    for key in ("test/rmse", "test/pcc", "cost/cpu_s", "mean/cost/bytes_up"):
        assert math.isfinite(run.data.metrics[key]), key
    assert [m.step for m in client.get_metric_history(run_id, "test/rmse")] == [1]
    # Artifacts went through the server's artifact proxy.
    assert {"config.yaml", "results.csv", "curves.png"} <= {
        a.path for a in client.list_artifacts(run_id)
    }
    with open(client.download_artifacts(run_id, "config.yaml")) as f:
        assert "method: FedRootAvg" in f.read()
