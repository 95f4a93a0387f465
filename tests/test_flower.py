"""fedlgr on a real Flower federation on localhost, started with the README's commands
(``fedlgr deploy``: a SuperLink with TLS and SuperNode authentication, two SuperNodes):
the same numbers as the in-process orchestrator, bytes measured on Flower's messages, an
unauthorised robot refused, a robot killed mid-round and back with its private state."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import threading
import time

import mlflow
import pytest

from fedlgr.federated.experiment import run_experiment
from fedlgr.federated.messages import nbytes
from fedlgr.federated.scope import initial_scholar
from tests.conftest import FAST, fast_config, results_csv
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
    assert not fed.leftovers()  # every process of the federation is gone


def settings(synth_dir, store, name: str) -> list[str]:
    return [f"data.path={synth_dir}", f"tracking.uri={store}", f"tracking.run_name={name}"]


def the_run(store: str, name: str, out: str) -> mlflow.entities.Run:
    client = mlflow.MlflowClient(store)
    experiment = client.get_experiment_by_name("fedlgr-debug")
    runs = client.search_runs([experiment.experiment_id], f"attributes.run_name = '{name}'")
    assert len(runs) == 1, out[-3000:]
    return runs[0]


def flower_run(federation, synth_dir, store, name, *overrides) -> tuple[mlflow.entities.Run, str]:
    proc = federation.run(FAST, [*settings(synth_dir, store, name), *overrides])
    out, _ = proc.communicate(timeout=900)
    assert proc.returncode == 0, out[-3000:]  # fedlgr deploy run: 0 only if completed
    return the_run(store, name, out), out


def history(client, run_id: str, key: str) -> list[tuple[int, float]]:
    return sorted((m.step, m.value) for m in client.get_metric_history(run_id, key))


def root_bytes(config) -> int:
    state = initial_scholar(config).state_dict()
    return nbytes(
        {k: v for k, v in state.items() if k.startswith("root.") and v.is_floating_point()}
    )


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
    flower, out = flower_run(federation, synth_dir, store, f"flower-{method[0]}", *method)
    assert flower.info.status == "FINISHED"
    assert flower.data.tags["runtime"] == "flower"
    local = run_experiment(
        fast_config(synth_dir, cache_dir, store, *method, f"tracking.run_name=local-{method[0]}")
    )
    client = mlflow.MlflowClient(store)
    local_run = client.get_run(local.run_id)
    assert local_run.data.tags["runtime"] == "fabric"
    # Every per-round score, means and per client, all tasks and each task: to 1e-5.
    keys = [k for k in local_run.data.metrics if k.split("/", 1)[-1].startswith(("test/", "task/"))]
    keys += [k for k in local_run.data.metrics if k.startswith(("test/", "task/"))]
    assert len(keys) > 40 and "test/client1/pcc" in keys
    if method[0] == "method=FedLGR":
        assert "task/client1/arrow/rmse" in keys and "lgr/fd_latent" in local_run.data.metrics
        keys += ["lgr/fd_latent", "lgr/client1/recon_mse"]
    rounds = 2
    for key in keys:
        ours, theirs = history(client, flower.info.run_id, key), history(client, local.run_id, key)
        assert [s for s, _ in ours] == [s for s, _ in theirs] and ours, key
        for (_, a), (_, b) in zip(ours, theirs, strict=True):
            assert math.isclose(a, b, rel_tol=0, abs_tol=1e-5), (key, a, b)
    # Bytes counted on the Flower messages (tensor payloads) = what one process reports:
    # FedRoot and FedLGR upload the root only.
    root = root_bytes(local.config)
    for c in (0, 1):
        up = history(client, flower.info.run_id, f"cost/client{c}/bytes_up")
        assert up == [(r, float(root)) for r in range(1, rounds + 1)]
        down = history(client, flower.info.run_id, f"cost/client{c}/bytes_down")
        assert down == history(client, local.run_id, f"cost/client{c}/bytes_down")
        assert down == [(1, 2.0 * root), (2, float(root))]  # the initial root, then the new
    assert "round/missing_clients" not in flower.data.metrics
    artifacts = [
        {a.path for a in client.list_artifacts(r)} for r in (flower.info.run_id, local.run_id)
    ]
    assert artifacts[0] == artifacts[1] and "results.csv" in artifacts[0]
    assert set(flower.data.params) == set(local_run.data.params)
    assert f"round {rounds}, evaluate: 2 of 2 replies" in out


def test_a_robot_without_a_registered_key_is_refused(federation, synth_dir):
    key = federation.node_key("intruder", register=False)
    proc = federation.start_supernode(
        "intruder", key, 0, synth_dir, ["--max-retries", "2", "--max-wait-time", "20"]
    )
    assert proc.wait(timeout=120) == 1
    assert "Failed to activate SuperNode" in federation.log("intruder")
    assert "No SuperNode found with the given public key" in federation.log("superlink")


def count(path, text: str) -> int:
    return path.read_text().count(text) if path.exists() else 0


def keep_starting(federation, run: subprocess.Popen, synth_dir) -> None:
    while run.poll() is None:
        node = federation.start_supernode("robot1", federation.keys["robot1"], 1, synth_dir)
        try:
            node.wait(timeout=10)  # refused: try again
        except subprocess.TimeoutExpired:
            return  # it is in
        time.sleep(2)


def test_a_robot_killed_mid_round_is_recorded_missing_and_rejoins_with_its_state(
    federation, synth_dir, store
):
    """SIGKILL robot 1's SuperNode and robot service while it trains in round 2: round 2
    aggregates robot 0 alone and records client 1 missing; robot 1 is started again at
    once (same key, same state folder) and takes part in round 3 with its private state,
    read back from disk by its new service."""
    robot = federation.robot_dir("robot1")
    log = robot / "robot.log"
    trained = count(log, "train received")
    restored = count(log, "private state restored")
    overrides = ["method=FedRootAvg", "federated.rounds=3", "deploy.min_clients=1"]
    overrides += ["deploy.round_timeout_s=120"]
    proc = federation.run(FAST, [*settings(synth_dir, store, "dropout"), *overrides])
    deadline = time.monotonic() + 300
    while count(log, "train received") < trained + 2:  # round 2's training has begun
        assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read()[-3000:]
        time.sleep(0.05)
    os.kill(int((robot / "robot.pid").read_text()), signal.SIGKILL)
    federation.procs["robot1"].kill()
    federation.procs["robot1"].wait()
    # Started again at once, as a supervisor (systemd, Restart=on-failure) would: the
    # SuperLink refuses the key until it has noticed the old connection is gone (two
    # missed heartbeats, ~1 min), so the SuperNode exits 1 until then.
    restart = threading.Thread(target=keep_starting, args=(federation, proc, synth_dir))
    restart.start()
    out, _ = proc.communicate(timeout=600)
    restart.join()
    assert proc.returncode == 0, out[-3000:]
    run = the_run(store, "dropout", out)
    client = mlflow.MlflowClient(store)
    assert run.info.status == "FINISHED"
    assert history(client, run.info.run_id, "round/missing_clients") == [(2, 1.0)]
    assert run.data.tags["fedlgr.missing"] == "round 2: client 1"
    assert "round 2, train: 1 of 2 replies" in out and "missing: client 1" in out
    rows = {(r["round"], r["client"]): r for r in results_csv(client, run.info.run_id)}
    assert rows[("2", "1")]["test_loss"] == "" and rows[("2", "0")]["test_loss"] != ""
    assert all(rows[(r, c)]["test_loss"] != "" for r in ("1", "3") for c in ("0", "1"))
    # Nothing logged was lost: every round's mean scores, robot 1's rounds 1 and 3.
    assert [s for s, _ in history(client, run.info.run_id, "test/loss")] == [1, 2, 3]
    assert [s for s, _ in history(client, run.info.run_id, "test/client1/loss")] == [1, 3]
    # Back with its private state (read from disk), sent the global root it had missed.
    assert count(log, "private state restored") == restored + 1
    root = root_bytes(fast_config(synth_dir, synth_dir, store, *overrides))
    assert history(client, run.info.run_id, "cost/client1/bytes_down")[-1] == (3, 2.0 * root)
    assert history(client, run.info.run_id, "cost/client0/bytes_down")[-1] == (3, float(root))
