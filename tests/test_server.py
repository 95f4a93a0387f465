"""End to end against a real ``mlflow server`` on localhost: ``fedlgr run --tracking-uri``
logs there, and the run reads back through the REST client."""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import time
import urllib.request

import mlflow
import pytest

from fedlgr.cli import main

from .conftest import FAST


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def mlflow_server(tmp_path_factory):
    """A real ``mlflow server`` on a free localhost port, shared by a test module's tests
    (it takes ~18 s to start); each test logs to its own experiment."""
    tmp_path = tmp_path_factory.mktemp("mlflow-server")
    port = free_port()
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mlflow",
            "server",
            "--backend-store-uri",
            f"sqlite:///{tmp_path}/server.db",
            "--artifacts-destination",
            str(tmp_path / "artifacts"),
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120  # ~18 s here (LIBRARY-NOTES)
    try:
        while True:
            if process.poll() is not None:
                pytest.fail(f"mlflow server exited: {process.stderr.read()[-2000:]}")
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2) as answer:
                    if answer.status == 200:
                        break
            except OSError:
                pass
            if time.monotonic() > deadline:
                pytest.fail("mlflow server did not answer /health within 120 s")
            time.sleep(0.5)
        yield url
    finally:
        process.terminate()
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()


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
