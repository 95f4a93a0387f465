"""fedlgr on a real Flower federation on localhost, started with the commands of docs/deployment.md
(``fedlgr deploy``: a SuperLink with TLS and SuperNode authentication, two SuperNodes):
the same numbers as the in-process orchestrator, bytes measured on Flower's messages, an
unauthorised robot refused, a robot killed mid-round and back with its private state."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import mlflow
import pytest
import torch

from fedlgr.core.messages import nbytes
from fedlgr.core.scope import initial_scholar
from fedlgr.core.server.side import ServerSide
from fedlgr.shell.deploy.roster import Roster
from fedlgr.shell.run import checkpoint as ckpt
from fedlgr.shell.run.experiment import run_experiment
from fedlgr.shell.tracking.liveness import process_alive
from tests.support.flower import Federation
from tests.support.runs import FAST, fast_config, results_csv

pytestmark = pytest.mark.slow

ROBOTS = ("robot0", "robot1", "robot2")  # on the roster as clients 0, 1, 2


@pytest.fixture(scope="module")
def federation(tmp_path_factory, synth_dir):
    fed = Federation(tmp_path_factory.mktemp("flower"))
    try:
        fed.start_superlink()
        fed.keys = {name: fed.node_key(name) for name in ROBOTS}
        for client, name in enumerate(ROBOTS[:2]):  # robot2 is started by the tests using it
            fed.start_supernode(name, fed.keys[name], client, synth_dir)
        yield fed
    finally:
        fed.stop()
    assert not fed.leftovers()  # every process of the federation is gone


DETAIL = ["tracking.detail_metrics=true"]  # per-client metrics in MLflow: compared here


def settings(synth_dir, store, name: str, federation=None) -> list[str]:
    out = [f"data.path={synth_dir}", f"tracking.uri={store}", f"tracking.run_name={name}"]
    out += DETAIL
    return out + ([f"deploy.roster={federation.roster}"] if federation is not None else [])


def the_run(store: str, name: str, out: str) -> mlflow.entities.Run:
    client = mlflow.MlflowClient(store)
    experiment = client.get_experiment_by_name("fedlgr-debug")
    runs = client.search_runs([experiment.experiment_id], f"attributes.run_name = '{name}'")
    assert len(runs) == 1, out[-3000:]
    return runs[0]


def flower_run(federation, synth_dir, store, name, *overrides) -> tuple[mlflow.entities.Run, str]:
    proc = federation.run(FAST, [*settings(synth_dir, store, name, federation), *overrides])
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
        ["method=FedLGR", "continual.rounds_per_task=1", "continual.lgr.epochs=3"],
        # control variates travel with the round, both ways, and steer rounds 2 and 3;
        # under client-level DP's clipping (no noise: the OS's noise differs from a seed's)
        # each update and control-variate change is clipped as one vector and weighs 1
        [
            "method=SCAFFOLD",
            "federated.rounds=3",
            "federated.dp.clip=0.05",
            "federated.dp.noise_multiplier=0",
            "federated.dp.delta=0.1",
        ],
        # one robot of two trains each round (seed 0: client 1, then 0, then 1), both are
        # scored, and the server scores the global model too (one run for both: ~1 min each)
        [
            "method=FedAvg",
            "federated.fraction=0.5",
            "federated.rounds=3",
            "federated.server_eval=on",
        ],
        # a robust aggregate over every robot's root (of two, Krum keeps robot 0's)
        ["method=FedRootKrum", "federated.rounds=2"],
    ],
    # FedRootAvg: the resume test
    ids=["FedLGR", "SCAFFOLD-dp-clipped", "FedAvg-half-server-eval", "FedRootKrum"],
)
def test_flower_runs_compute_what_one_process_computes(
    federation, synth_dir, cache_dir, store, method, request
):
    name = request.node.callspec.id  # one run name per case: two cases are FedAvg
    flower, out = flower_run(federation, synth_dir, store, f"flower-{name}", *method)
    assert flower.info.status == "FINISHED"
    assert flower.data.tags["runtime"] == "flower"
    local = run_experiment(
        fast_config(
            synth_dir, cache_dir, store, *method, *DETAIL, f"tracking.run_name=local-{name}"
        )
    )
    rounds = len(local.rounds)
    assert_computes_what_one_process_computes(store, flower, local, rounds)
    assert f"round {rounds}, evaluate: 2 of 2 replies" in out


def assert_computes_what_one_process_computes(store, flower, local, rounds: int) -> None:
    """The Flower run's per-round scores, bytes, artifacts and params are the in-process
    run's (``local``)."""
    client = mlflow.MlflowClient(store)
    local_run = client.get_run(local.run_id)
    assert local_run.data.tags["runtime"] == "fabric"
    # Every per-round score, means and per client, all tasks and each task: to 1e-5.
    keys = [k for k in local_run.data.metrics if k.split("/", 1)[-1].startswith(("test/", "task/"))]
    keys += [k for k in local_run.data.metrics if k.startswith(("test/", "task/"))]
    assert len(keys) > 40 and "test/client1/pcc" in keys
    if local.config.method == "FedLGR":
        assert "task/client1/arrow/rmse" in keys and "lgr/fd_latent" in local_run.data.metrics
        keys += ["lgr/fd_latent", "lgr/client1/recon_mse"]
    if local.config.federated.dp.enabled:  # the clip norm each round (no epsilon: no noise)
        assert "privacy/epsilon" not in local_run.data.metrics
        keys += ["privacy/clip"]
    if local.config.federated.server_evaluates:  # before round 1 (step 0), then every round
        keys += [k for k in local_run.data.metrics if k.startswith("server/")]
        assert "server/test/rmse" in keys
        assert history(client, flower.info.run_id, "server/test/rmse")[0][0] == 0
    assert len(history(client, flower.info.run_id, "cost/server_cpu_s")) == rounds
    for key in keys:
        # every point, unsorted by step: a round logged twice (a resume) would show here
        ours = sorted((m.step, m.value) for m in client.get_metric_history(flower.info.run_id, key))
        theirs = history(client, local.run_id, key)
        assert [s for s, _ in ours] == [s for s, _ in theirs] and ours, (key, ours)
        for (_, a), (_, b) in zip(ours, theirs, strict=True):
            assert math.isclose(a, b, rel_tol=0, abs_tol=1e-5), (key, a, b)
    # Bytes counted on the Flower messages (tensor payloads) = what one process reports:
    # FedRoot and FedLGR upload the root only.
    root = root_bytes(local.config)
    for c in (0, 1):
        up = history(client, flower.info.run_id, f"cost/client{c}/bytes_up")
        assert up == history(client, local.run_id, f"cost/client{c}/bytes_up")
        down = history(client, flower.info.run_id, f"cost/client{c}/bytes_down")
        assert down == history(client, local.run_id, f"cost/client{c}/bytes_down")
        if local.config.federated.scope == "root":  # the initial root, then the new one
            assert up == [(r, float(root)) for r in range(1, rounds + 1)]
            assert down == [(1, 2.0 * root)] + [(r, float(root)) for r in range(2, rounds + 1)]
    assert "round/missing_clients" not in client.get_run(flower.info.run_id).data.metrics
    artifacts = [
        {a.path for a in client.list_artifacts(r)} for r in (flower.info.run_id, local.run_id)
    ]
    assert artifacts[0] == artifacts[1] and "results.csv" in artifacts[0]
    # the same settings, and a Flower run's deploy.* settings (only it uses them)
    deploy = {p for p in flower.data.params if p.startswith("deploy.")}
    assert set(flower.data.params) - deploy == set(local_run.data.params)
    assert "deploy.roster" in deploy and not any(
        p.startswith("deploy.") for p in local_run.data.params
    )


def count(path, text: str) -> int:
    return path.read_text().count(text) if path.exists() else 0


def wait_online(federation, name: str, timeout: float = 120) -> None:
    """Until the latest start of SuperNode ``name`` is connected (Flower logs its node id)."""
    deadline = time.monotonic() + timeout
    while "SuperNode ID" not in federation.log(name):
        assert federation.procs[name].poll() is None, federation.log(name)[-2000:]
        assert time.monotonic() < deadline, federation.log(name)[-2000:]
        time.sleep(0.2)


QUICK = ["--max-retries", "1", "--max-wait-time", "5"]  # a refused SuperNode exits in ~5 s


def start_until_online(
    federation, name: str, synth_dir, going=lambda: True, env: dict | None = None
) -> bool:
    """Start ``name``'s SuperNode (its roster slot) again and again until the SuperLink
    takes it - a key whose last connection has not yet timed out is refused for two
    heartbeats (~1 min with Flower's, ~20 s with the tests' --heartbeat-s 10) and the
    SuperNode exits 1 - as a supervisor (systemd, Restart=on-failure) would.
    True once it is online (its log names its node id: a positive sign, not a guess from
    how long it has lived, which a loaded machine stretches); False if ``going()`` turns
    false first."""
    deadline = time.monotonic() + 300
    while going():
        assert time.monotonic() < deadline, federation.log(name)[-2000:]
        keys = federation.keys[name]
        node = federation.start_supernode(name, keys, None, synth_dir, QUICK, env)
        while node.poll() is None:
            if "SuperNode ID" in federation.log(name):
                return True
            if not going():
                return False
            time.sleep(0.2)
        time.sleep(1)  # refused: try again
    return False


def ensure_online(federation, synth_dir, *names: str) -> None:
    """Robots a test needs: any whose SuperNode an earlier test left stopped is started."""
    for name in names:
        if federation.procs[name].poll() is not None:
            assert start_until_online(federation, name, synth_dir), name


def stop(federation, name: str) -> None:
    proc = federation.procs[name]
    proc.terminate()
    proc.wait(timeout=30)


def end_service(federation, name: str) -> None:
    """SIGTERM to ``name``'s robot service, if one runs (it outlives its SuperNode), and wait until
    it is gone: the robot's next message starts a new one, in its SuperNode's environment."""
    service = federation.robot_dir(name) / "robot.pid"
    with contextlib.suppress(ProcessLookupError, FileNotFoundError, ValueError):
        os.kill(int(service.read_text()), signal.SIGTERM)
    deadline = time.monotonic() + 30
    while service.exists():  # it removes its pid file as it leaves
        assert time.monotonic() < deadline, f"{name}'s robot service did not leave"
        time.sleep(0.1)


def test_roster_keeps_strangers_unrostered_keys_and_claimed_slots_out_of_a_run(
    federation, synth_dir, store
):
    """Three intruders and a run of three clients: a SuperNode whose key was never
    registered (refused by the SuperLink), one whose key is registered but not on the
    roster (online, never sent a message), and robot2 - slot 2 on the roster - whose
    SuperNode claims client 0 (its ClientApp refuses the run's slot before its service
    starts). None takes part; the run goes on with robots 0 and 1 and says why."""
    stranger = federation.node_key("stranger", register=False, roster=False)
    unrostered = federation.node_key("unrostered", roster=False)
    assert "unrostered" not in federation.roster.read_text()
    options = ["--max-retries", "2", "--max-wait-time", "20"]
    strange = federation.start_supernode("stranger", stranger, None, synth_dir, options)
    federation.start_supernode("unrostered", unrostered, 1, synth_dir)
    federation.start_supernode("robot2", federation.keys["robot2"], 0, synth_dir)
    try:
        assert strange.wait(timeout=120) == 1
        assert "Failed to activate SuperNode" in federation.log("stranger")
        assert "No SuperNode found with the given public key" in federation.log("superlink")
        for name in ("unrostered", "robot2"):
            wait_online(federation, name)
        overrides = ["method=FedRootAvg", "federated.rounds=1", "data.clients=3"]
        proc = federation.run(FAST, [*settings(synth_dir, store, "roster", federation), *overrides])
        out, _ = proc.communicate(timeout=600)
    finally:
        for name in ("unrostered", "robot2"):
            stop(federation, name)
    assert proc.returncode == 0, out[-3000:]  # 2 of 3 robots: the default quorum
    run = the_run(store, "roster", out)
    assert "is not on the roster" in out and "it is sent no work" in out
    assert "robot2 (client 2) failed: " in out and "the run's roster gives its key client 2" in out
    assert "refused node" in out and "robot2 (client 2) claims another slot" in out
    refused = run.data.tags["fedlgr.refused"]
    assert "is not on the roster" in refused and "robot2 (client 2) claims another slot" in refused
    assert run.data.tags["fedlgr.robots"].startswith("robot0 (client 0), robot1 (client 1)")
    client = mlflow.MlflowClient(store)
    assert history(client, run.info.run_id, "round/missing_clients") == [(1, 1.0)]
    assert run.data.tags["fedlgr.missing_robots"] == "round 1: client 2"
    # Nothing reached the unrostered node's robot; robot2's robot never started.
    for name in ("unrostered", "robot2"):
        assert count(federation.robot_dir(name) / "robot.log", "received") == 0, name
        assert not list(federation.robot_dir(name).glob("run-*")), name
    rows = {(r["round"], r["client"]): r for r in results_csv(client, run.info.run_id)}
    assert rows[("1", "0")]["test_loss"] != "" and rows[("1", "1")]["test_loss"] != ""
    assert rows[("1", "2")]["test_loss"] == ""


BYZANTINE = Path(__file__).parent / "support" / "byzantine"  # its sitecustomize alters replies


def test_a_byzantine_robot_is_refused_named_and_the_global_model_is_the_one_without_it(
    federation, synth_dir, cache_dir, store
):
    """robot2 (client 2) is on the roster (at most 100 scenes) and trains honestly, but
    alters every upload it sends (SCAFFOLD: a control-variate change goes with each): NaN
    (round 1), x 1e6 tensors (round 2), a tensor cut short (round 3), a sample count of 10^12
    (round 4), client 0's (round 5), its payload x 8 (round 6, issue 50) and round 6's
    upload again (round 7, issue 50); with round 2's
    upload it reports its round-1 scores as NaN, with round 3's its round-2 scores as RMSE
    0.01 and PCC 0.99 - which the server, scoring the same whole model, refuses (issue 50).
    Each is refused and robot2 named, in the console, MLflow and
    results.csv (a robot whose upload is not its own cannot be scored in that round); the run
    completes with robots 0 and 1, and the global model - the server's own scores of it
    each round, and every robot's - is the one-process run's whose client 2 sends x 1e6
    every round (refused there by its norm: the same mean without it)."""
    ensure_online(federation, synth_dir, "robot0", "robot1")
    roster = Roster.read(federation.roster)
    roster.members = [
        dataclasses.replace(m, scenes=100) if m.name == "robot2" else m for m in roster.members
    ]
    roster.write()
    plan = "nan,scale+scores,truncate+liar,count,client,payload8,replay"
    env = {"PYTHONPATH": str(BYZANTINE), "FEDLGR_BYZANTINE": plan}
    assert start_until_online(federation, "robot2", synth_dir, env=env)
    method = ["method=SCAFFOLD", "federated.server_eval=on", "data.clients=3"]
    method += ["federated.rounds=7", "seed=2"]  # seed 2: the one-process run's client 2
    try:
        flower, out = flower_run(federation, synth_dir, store, "byzantine", *method)
    finally:
        stop(federation, "robot2")
        end_service(federation, "robot2")  # no altered robot left
    robot_log = (federation.robot_dir("robot2") / "robot.log").read_text()
    assert "byzantine: train reply 2: scale+scores" in robot_log  # it did alter them
    who = "refused robot2 (client 2)'s"
    assert f"round 1/7: {who} upload: " in out and "holds values that are not finite" in out
    # x 1e6 tensors beside an honest payload: the payload is no longer their change
    assert f"round 2/7: {who} upload: scaffold payload is not its update's control-" in out
    assert f"round 3/7: {who} upload: cannot be read (ValueError: " in out
    assert f"round 4/7: {who} upload: sample count 1000000000000 exceeds its 100" in out
    assert f"round 5/7: {who} upload: it claims to be client 0's" in out
    assert f"round 6/7: {who} upload: scaffold payload is not its update's control-" in out
    assert f"round 7/7: {who} upload: stale: identical to an upload it sent before" in out
    [first] = [line for line in out.splitlines() if line.startswith(f"round 1/7: {who}")]
    assert "; scores: " in first and "= nan is not finite" in first, first  # one line each
    [second] = [line for line in out.splitlines() if line.startswith(f"round 2/7: {who}")]
    assert "; scores: test/" in second, second
    assert (
        "scores: test/loss = 0.01 where the server's own evaluation of the same model gives "
        in second
    )
    client = mlflow.MlflowClient(store)
    run_id = flower.info.run_id
    assert flower.info.status == "FINISHED"
    assert history(client, run_id, "faults/refused") == [(r, 1.0) for r in range(1, 8)]
    assert flower.data.tags["fedlgr.not_taken"].startswith("round 1: robot2 (client 2) (upload: ")
    # its round-1 and round-2 scores refused, its round-3 and round-5 uploads not its own
    missing = [(1, 1.0), (2, 1.0), (3, 1.0), (5, 1.0)]  # its round-2 scores: lies
    assert history(client, run_id, "round/missing_clients") == missing
    faults = {(r["round"], r["client"]): r["fault"] for r in results_csv(client, run_id)}
    first = faults[("1", "2")]
    assert first.startswith("refused upload: ") and "; scores: " in first, first
    assert faults[("3", "2")].startswith("refused upload: cannot be read (ValueError: ")
    assert all(faults[(str(r), c)] == "" for r in range(1, 8) for c in ("0", "1"))
    byzantine = ["federated.faults.byzantine=1", "federated.faults.attack=scale"]
    local = run_experiment(
        fast_config(
            synth_dir,
            cache_dir,
            store,
            *method,
            *byzantine,
            "federated.faults.scale=1e6",
            *DETAIL,
            "tracking.run_name=local-byzantine",
        )
    )
    assert local.config.federated.faults.byzantine == 1
    assert history(client, local.run_id, "faults/refused") == [(r, 1.0) for r in range(1, 8)]
    local_run = client.get_run(local.run_id)
    keys = [k for k in local_run.data.metrics if k.startswith("server/test/")]
    keys += [k for k in local_run.data.metrics if k.startswith(("test/client0/", "test/client1/"))]
    assert "server/test/rmse" in keys and "test/client1/pcc" in keys
    for key in [*keys, "test/client2/rmse", "test/client2/pcc"]:
        ours = history(client, run_id, key)
        theirs = [p for p in history(client, local.run_id, key) if p[0] > 0]
        if "client2" in key:  # not scored in rounds 1, 2, 3 and 5
            theirs = [p for p in theirs if p[0] not in (1, 2, 3, 5)]
        ours = [p for p in ours if p[0] > 0]
        assert [s for s, _ in ours] == [s for s, _ in theirs] and ours, (key, ours, theirs)
        for (_, a), (_, b) in zip(ours, theirs, strict=True):
            assert math.isclose(a, b, rel_tol=0, abs_tol=1e-5), (key, a, b)


def test_a_robot_killed_mid_round_is_recorded_missing_and_rejoins_with_its_state(
    federation, synth_dir, store
):
    """Three robots, default settings (quorum: 2 of 3). SIGKILL robot 1's SuperNode and
    robot service while it answers its second message - round 1's evaluation and round
    2's training: rounds 1 and 2 go on without its row and name it; robot 1 is started
    again at once (same key, same state folder; refused for ~20 s, until the SuperLink
    has missed two of its 10-s heartbeats) and takes part in the last round with its private
    state, read back from disk by its new service. Rounds take ~1 s once robot 1 is
    declared lost: 24 of them leave it the time to come back (it was back by round 8 of 20
    on a quiet machine, by round 5 before the 10-s heartbeat)."""
    robot = federation.robot_dir("robot1")
    log = robot / "robot.log"
    trained = count(log, "train received")
    restored = count(log, "private state restored")
    ensure_online(federation, synth_dir, "robot0", "robot1")
    assert start_until_online(federation, "robot2", synth_dir)
    rounds = 24
    overrides = ["method=FedRootAvg", f"federated.rounds={rounds}", "data.clients=3"]
    overrides += ["deploy.round_timeout_s=120"]
    proc = federation.run(FAST, [*settings(synth_dir, store, "dropout", federation), *overrides])
    deadline = time.monotonic() + 300
    while count(log, "train received") < trained + 2:  # round 2's training has begun
        assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read()[-3000:]
        time.sleep(0.05)
    os.kill(int((robot / "robot.pid").read_text()), signal.SIGKILL)
    federation.procs["robot1"].kill()
    federation.procs["robot1"].wait()
    # Started again at once: the SuperLink refuses the key until it has noticed the old
    # connection is gone (two missed heartbeats, ~20 s), so the SuperNode exits 1 until then.
    back = []
    restart = threading.Thread(
        target=lambda: back.append(
            start_until_online(federation, "robot1", synth_dir, lambda: proc.poll() is None)
        )
    )
    restart.start()
    try:
        out, _ = proc.communicate(timeout=600)
    finally:
        restart.join()
        stop(federation, "robot2")
    assert proc.returncode == 0, out[-3000:]
    assert back == [True], "robot1 was not back online before the run ended"
    run = the_run(store, "dropout", out)
    client = mlflow.MlflowClient(store)
    assert run.info.status == "FINISHED"
    missed = history(client, run.info.run_id, "round/missing_clients")
    assert missed[:2] == [(1, 1.0), (2, 1.0)] and all(r < rounds for r, _ in missed), missed
    assert run.data.tags["fedlgr.missing"].startswith("round 1: client 1; round 2: client 1")
    assert run.data.tags["fedlgr.missing_robots"].startswith(
        "round 1: robot1 (client 1); round 2: robot1 (client 1)"
    )
    assert "round 1, evaluate + round 2 train: 2 of 3 replies" in out
    # the SuperLink answers for a robot it has lost (an error reply), or it stays silent
    named = (
        "round 1, evaluate + round 2 train: robot1 (client 1) failed: ",
        "no reply from robot1",
    )
    assert any(text in out for text in named), out[-3000:]
    assert "missing: client 1" in out
    rows = {(r["round"], r["client"]): r for r in results_csv(client, run.info.run_id)}
    assert rows[("2", "1")]["test_loss"] == "" and rows[("2", "0")]["test_loss"] != ""
    assert all(rows[(str(rounds), c)]["test_loss"] != "" for c in ("0", "1", "2"))
    # Nothing logged was lost: every round's mean scores, robot 1's last round.
    steps = list(range(1, rounds + 1))
    assert [s for s, _ in history(client, run.info.run_id, "test/loss")] == steps
    assert [s for s, _ in history(client, run.info.run_id, "test/client1/loss")][-1] == rounds
    # Back with its private state (read from disk), sent the global root it had missed.
    assert count(log, "private state restored") == restored + 1
    root = root_bytes(fast_config(synth_dir, synth_dir, store, *overrides))
    first_back = history(client, run.info.run_id, "cost/client1/bytes_down")[0]
    assert 3 <= first_back[0] <= rounds and first_back[1] == 2.0 * root
    assert history(client, run.info.run_id, "cost/client0/bytes_down")[-1] == (rounds, float(root))


def apps(federation, name: str = "flwr-serverapp") -> list[int]:
    """The app processes of this federation: its ServerApps (``flwr-serverapp``, started by the
    SuperLink's SuperExec) or its ClientApps (``flwr-clientapp``, by the SuperNodes')."""
    found = []
    for pid in federation.leftovers():
        with contextlib.suppress(OSError):
            # forked by fedlgr's executor: named as Flower's own process
            if Path(f"/proc/{pid}/comm").read_text().strip() == name:
                found.append(pid)
    return found


def test_a_killed_serverapp_resumes_in_its_mlflow_run_and_computes_what_one_process_computes(
    federation, synth_dir, cache_dir, store
):
    """FedRootAvg, 6 rounds (a round is ~1 s: the kill must land before the end): SIGKILL
    of the ServerApp once round 1 is logged and checkpointed; ``fedlgr deploy run CONFIG
    --resume`` continues the same MLflow run from its newest checkpoint, the robots from
    their own state (a robot asked again what it answered last sends the same reply).
    Every round is logged once, with the in-process run's scores to 1e-5
    (an uninterrupted Flower run gives them: the test above, for FedLGR), bytes,
    artifacts and params."""
    ensure_online(federation, synth_dir, "robot0", "robot1")
    method = ["method=FedRootAvg", "federated.rounds=6"]
    base = [*settings(synth_dir, store, "resumed", federation), *method]
    proc = federation.run(FAST, base)
    client = mlflow.MlflowClient(store)
    deadline = time.monotonic() + 400
    while True:
        assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read()[-3000:]
        experiment = client.get_experiment_by_name("fedlgr-debug")  # None until created
        ids = [experiment.experiment_id] if experiment else []
        runs = client.search_runs(ids, "attributes.run_name = 'resumed'") if ids else []
        # round 1 logged and checkpointed (a kill between the two leaves nothing to resume:
        # the resume refuses, rightly, and a round is ~1 s here)
        if runs and history(client, runs[0].info.run_id, "test/loss"):
            run_id = runs[0].info.run_id
            folder = Path(store.removeprefix("sqlite:///")).parent / "checkpoints" / run_id
            if list(folder.glob("round-*.ckpt")):
                break
        time.sleep(0.05)
    [serverapp] = apps(federation)
    os.kill(serverapp, signal.SIGKILL)
    proc.kill()  # the log stream (what Ctrl-C stops); the run on the SuperLink is dead
    proc.communicate()
    resumed = federation.run(FAST, [*base, "--resume"])
    out, _ = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, out[-3000:]
    assert f"resuming run {run_id} after round" in out
    run = client.get_run(run_id)
    assert run.info.status == "FINISHED"
    # Issue 50: resuming it again streamed the ServerApp's traceback before the one-line error;
    # now it is refused before any Flower run starts.
    again = federation.run(FAST, [*base, "--resume", run_id], stderr=subprocess.PIPE)
    out, err = again.communicate(timeout=120)
    assert again.returncode == 1 and out == "", out
    finished = f"--resume: run {run_id} has finished; there is nothing to resume"
    assert err == f"fedlgr: error: {finished}\n"
    local = run_experiment(
        fast_config(
            synth_dir, cache_dir, store, *method, *DETAIL, "tracking.run_name=local-resumed"
        )
    )
    assert_computes_what_one_process_computes(store, run, local, 6)


def test_a_killed_serverapps_clientapps_end_with_its_run_and_robot_services_with_their_supernode(
    federation, synth_dir, store
):
    """Issue 50's tester: after a ServerApp's SIGKILL each robot kept its forked ClientApp
    (~100 MB) for 12+ minutes - as long as its training for the dead run took - and a robot
    service (~1 GB) stayed 15 minutes after its SuperNode stopped. Here the robots train for
    minutes (5000 epochs); the ServerApp is killed once both train: the SuperLink ends the run at
    once (the executor reports the kill), each SuperNode stops its ClientApp within seconds; then
    the SuperNodes are stopped and their robot services leave within seconds, mid-training."""
    names = ("robot0", "robot1")
    ensure_online(federation, synth_dir, *names)
    logs = {name: federation.robot_dir(name) / "robot.log" for name in names}
    received = {name: count(log, "train received") for name, log in logs.items()}
    answered = {name: count(log, "train answered") for name, log in logs.items()}
    slow = ["method=FedAvg", "train.epochs=5000", "deploy.round_timeout_s=900"]
    proc = federation.run(FAST, [*settings(synth_dir, store, "killed", federation), *slow])
    deadline = time.monotonic() + 300
    while any(count(log, "train received") == received[name] for name, log in logs.items()):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read()[-3000:]
        time.sleep(0.1)
    [serverapp] = apps(federation)
    os.kill(serverapp, signal.SIGKILL)
    killed = time.monotonic()
    proc.kill()  # the log stream
    proc.communicate()
    said = "is no longer running on the SuperLink: 1 ClientApp process(es) stopped"
    while apps(federation, "flwr-clientapp") or not all(said in federation.log(n) for n in names):
        assert time.monotonic() - killed < 30, federation.log("robot0")[-2000:]
        time.sleep(0.2)
    ended = time.monotonic() - killed
    assert {name: count(log, "train answered") for name, log in logs.items()} == answered
    killed_line = "the ServerApp process was killed (SIGKILL): its task is reported failed"
    assert killed_line in federation.log("superlink")
    services = {name: int((federation.robot_dir(name) / "robot.pid").read_text()) for name in names}
    for name in names:
        stop(federation, name)
    stopped = time.monotonic()
    while any(process_alive(pid) for pid in services.values()):  # a zombie is not
        assert time.monotonic() - stopped < 30, logs["robot0"].read_text()[-2000:]
        time.sleep(0.2)
    left = time.monotonic() - stopped
    for name, log in logs.items():
        assert f"SuperNode {federation.procs[name].pid} has ended: leaving" in log.read_text()
        assert not (federation.robot_dir(name) / "robot.pid").exists()
    print(f"ClientApps ended {ended:.1f} s after the kill, services {left:.1f} s after their stop")


def newest_global(store: str, run_id: str) -> dict:
    """The global tensors of an in-process run's newest checkpoint (while it runs: a
    finished run's checkpoints are removed)."""
    folder = Path(store.removeprefix("sqlite:///")).parent / "checkpoints" / run_id
    newest = max(folder.glob("round-*.ckpt"), key=lambda p: int(p.stem.split("-")[1]))
    return ckpt.load(newest)["server"]["global"]


def test_secure_aggregation_gives_the_plain_mean_within_its_quantisation_bound(
    federation, synth_dir, cache_dir, store
):
    """FedAvg with deploy.secagg on two robots, one round: the server sees the sum of the
    robots' masked vectors only (SecAgg+: 4 exchanges, then the evaluation), and its new
    global tensors are the in-process run's (the same uploads, same seed) within the
    quantisation bound it records (secagg/error_bound: robots x 2c/Q x max_samples / the
    summed sample count; docs/deployment.md) plus one float32 rounding of each side."""
    ensure_online(federation, synth_dir, "robot0", "robot1")
    secagg = ["deploy.secagg.enabled=true", "deploy.secagg.max_samples=100"]
    flower, out = flower_run(federation, synth_dir, store, "secagg", "method=FedAvg", *secagg)
    assert "round 1, secure train: 2 of 2 robots in the sum" in out, out[-3000:]
    ids, kept = [], []
    run_experiment(
        fast_config(synth_dir, cache_dir, store, "method=FedAvg", "tracking.run_name=local-sa"),
        on_start=ids.append,
        on_round=lambda _round, _metrics: kept.append(newest_global(store, ids[0])),
    )
    client = mlflow.MlflowClient(store)
    [(_, bound)] = history(client, flower.info.run_id, "secagg/error_bound")
    assert 0 < bound < 1e-4
    [theirs] = kept
    worst = 0.0
    for robot, slot in (("robot0", 0), ("robot1", 1)):  # the global tensors each scored
        state = federation.robot_dir(robot) / f"run-{flower.info.run_id}" / f"client-{slot}.ckpt"
        ours = ckpt.load(state)["client"]["model"]
        for key, value in theirs.items():
            error = (ours[key].double() - value.double()).abs()
            # the bound, and each side's float64 -> float32 rounding (half an ulp each)
            assert bool((error <= bound + 2.0**-23 * value.double().abs()).all()), key
            worst = max(worst, float(error.max()))
    print(f"secagg: max error {worst:.3g}, bound {bound:.3g}")
    # each robot's bytes up: its masked vector (int64 per value: twice the float32 upload)
    up = history(client, flower.info.run_id, "cost/client0/bytes_up")[0][1]
    assert up > 2 * sum(v.numel() * 4 for v in theirs.values())
    # the key stages' messages, counted; the robots' training figures came in the clear
    assert history(client, flower.info.run_id, "secagg/setup_bytes_up")[0][1] > 0
    rows = {(r["round"], r["client"]): r for r in results_csv(client, flower.info.run_id)}
    assert rows[("1", "0")]["train_loss"] != "" and rows[("1", "1")]["test_loss"] != ""


def test_under_secagg_a_huge_masked_update_is_refused_at_the_aggregate(
    federation, synth_dir, store
):
    """SecAgg+ on three robots, one round, the server scoring the global model too: robot2
    trains honestly, then sends its update x 1000, unclipped (FEDLGR_BYZANTINE=secscale; issue
    50: such an upload took the RMSE to 59,811 in one round, unrefused). The server cannot tell
    whose it is, but the sum's mean update is far over deploy.secagg.norm_bound, which honest
    robots clip to: the sum is refused, the round and both norms named, and counted; the global
    model stays the initial one (the server's scores of round 1 are those of round 0, and the
    global tensors each robot scored are the initial ones) and the run completes."""
    ensure_online(federation, synth_dir, "robot0", "robot1")
    end_service(federation, "robot2")  # a service started without the Byzantine hook
    env = {"PYTHONPATH": str(BYZANTINE), "FEDLGR_BYZANTINE": "secscale"}
    assert start_until_online(federation, "robot2", synth_dir, env=env)
    log = federation.robot_dir("robot2") / "robot.log"
    altered = count(log, "byzantine: train reply 1: secscale")
    method = ["method=FedAvg", "data.clients=3", "federated.server_eval=on"]
    method += ["deploy.secagg.enabled=true"]
    try:
        flower, out = flower_run(federation, synth_dir, store, "secagg-huge", *method)
    finally:
        stop(federation, "robot2")
        end_service(federation, "robot2")  # no altered robot left
    assert count(log, "byzantine: train reply 1: secscale") == altered + 1
    assert "round 1, secure train: 3 of 3 robots in the sum" in out, out[-3000:]
    refused = "round 1: the secure sum of 3 robots is refused: its mean update's norm "
    [line] = [line for line in out.splitlines() if line.startswith(refused)]
    norm = float(line.removeprefix(refused).split()[0])
    assert norm > 10 * 100, line  # honest ones: ~15 (docs/deployment.md)
    assert " is over deploy.secagg.norm_bound=100 (+" in line, line
    assert line.endswith("; the global model stays"), line
    print(line)
    client = mlflow.MlflowClient(store)
    run_id = flower.info.run_id
    assert flower.info.status == "FINISHED"
    assert history(client, run_id, "secagg/sum_refused") == [(1, 1.0)]
    assert flower.data.tags["fedlgr.secagg_refused"].startswith("round 1: its mean update's norm ")
    keys = [k for k in flower.data.metrics if k.startswith("server/test/")]
    assert "server/test/rmse" in keys
    for key in keys:  # the same tensors scored on the same scenes: the same figures
        [(step0, before), (step1, after)] = history(client, run_id, key)
        assert (step0, step1) == (0, 1) and after == before, key
    initial = ServerSide(fast_config(synth_dir, synth_dir, store, *method)).global_weights
    for robot, slot in (("robot0", 0), ("robot1", 1)):
        state = federation.robot_dir(robot) / f"run-{run_id}" / f"client-{slot}.ckpt"
        scored = ckpt.load(state)["client"]["model"]
        assert all(torch.equal(scored[k], v) for k, v in initial.items()), robot


def test_a_secure_round_recovers_a_robot_killed_after_the_round_before(
    federation, synth_dir, store
):
    """SecAgg+ on three robots, two rounds; robot2's SuperNode and robot service are killed as
    round 1 ends (issue 50: the run failed, "Not enough shares to recover secret"). The SuperLink
    still lists robot2 as round 2 begins, so it is sent SecAgg+'s setup, and is lost (~20 s:
    two missed heartbeats) before it shares its keys; round 2 unmasks the sum of the two robots
    left - no share of robot2's key is needed: no vector was masked with it - names robot2,
    and the run completes."""
    ensure_online(federation, synth_dir, "robot0", "robot1")
    assert start_until_online(federation, "robot2", synth_dir)
    overrides = ["method=FedAvg", "federated.rounds=2", "data.clients=3"]
    overrides += ["deploy.secagg.enabled=true", "deploy.round_timeout_s=60"]
    base = settings(synth_dir, store, "secagg-dropout", federation)
    proc = federation.run(FAST, [*base, *overrides])
    seen = []
    for line in proc.stdout:  # the run's log, as it comes
        seen.append(line)
        if line.startswith("round 1/2: "):  # round 1 recorded: round 2 begins
            break
    service = federation.robot_dir("robot2") / "robot.pid"
    os.kill(int(service.read_text()), signal.SIGKILL)
    federation.procs["robot2"].kill()
    federation.procs["robot2"].wait()
    rest, _ = proc.communicate(timeout=600)
    out = "".join(seen) + rest
    assert proc.returncode == 0, out[-3000:]
    assert "round 1, secure train: 3 of 3 robots in the sum" in out, out[-3000:]
    [line] = [line for line in out.splitlines() if line.startswith("round 2, secure train: ")]
    assert line.startswith("round 2, secure train: 2 of 3 robots in the sum"), line
    assert any(f"; robot2 (client 2): {stage}: " in line for stage in ("setup", "share_keys")), line
    print(line)
    run = the_run(store, "secagg-dropout", out)
    client = mlflow.MlflowClient(store)
    run_id = run.info.run_id
    assert run.info.status == "FINISHED"
    assert history(client, run_id, "secagg/robots") == [(1, 3.0), (2, 2.0)]
    assert history(client, run_id, "secagg/sum_refused") == [(1, 0.0), (2, 0.0)]  # unmasked
    assert run.data.tags["fedlgr.missing_robots"] == "round 2: robot2 (client 2)"
    # the survivors' sum moved the global model that they scored
    [(round1, before), (round2, after)] = history(client, run_id, "test/client0/loss")
    assert (round1, round2) == (1, 2) and after != before
