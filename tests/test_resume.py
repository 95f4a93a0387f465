"""Checkpoints and ``--resume``: a run killed outright continues bit for bit in the same
MLflow run; checkpoints are whole or absent; a resume is refused when it cannot be right."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch

from fedlgr.errors import FedlgrError
from fedlgr.shell.cli import main
from fedlgr.shell.data.synth import synthesize
from fedlgr.shell.run import checkpoint as ckpt
from fedlgr.shell.run.experiment import run_experiment
from tests.support.processes import (
    BIG_CHECKPOINT,
    DETAIL,
    Child,
    metric_steps,
    only_run,
    partial_checkpoint,
    run_args,
)
from tests.support.runs import Interrupt, csv_rounds, results_csv
from tests.support.runs import fast_config as _fast_config


def fast_config(synth_dir, cache_dir, store, *overrides):
    return _fast_config(synth_dir, cache_dir, store, DETAIL, *overrides)


REPO = Path(__file__).resolve().parents[1]
# Measured, never equal between two runs (system/*: MLflow's machine-wide system metrics).
TIMING = ("cpu_s", "wall_s", "seconds", "gpu_", "system/")
FEDLGR = ["method=FedLGR", "continual.rounds_per_task=2", "continual.lgr.epochs=5"]
NR = ["method=FedRoot-NR", "continual.rounds_per_task=2", "continual.nr.memory=6"]


def _start(args, cwd) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen(
        [sys.executable, "-m", "fedlgr", "run", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def _finish(args, cwd) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run(
        [sys.executable, "-m", "fedlgr", "run", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def _kill_when(process: subprocess.Popen, ready, what: str, limit: float = 300) -> None:
    deadline = time.monotonic() + limit
    while not ready():
        assert process.poll() is None, f"the run ended before {what}: {process.stderr.read()}"
        assert time.monotonic() < deadline, f"{what} never happened"
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGKILL)  # a real kill: nothing of the run's cleans up
    process.wait()


def _killed_after_checkpoint(args, cwd: Path, round_: int = 2) -> Path:
    """Start ``fedlgr run ARGS`` and SIGKILL it once its round-``round_`` checkpoint is
    written; the run's checkpoint folder."""
    name = f"round-{round_:04d}.ckpt"
    root = cwd / "checkpoints"
    process = _start(args, cwd)
    _kill_when(
        process,
        lambda: any((p / name).exists() for p in root.glob("*")),
        f"the checkpoint of round {round_}",
    )
    (folder,) = (p for p in root.glob("*") if (p / name).exists())
    return folder


def _only_run(store: str, experiment: str = "fedlgr-debug", name: str | None = None):
    client = mlflow.MlflowClient(store)
    eid = client.get_experiment_by_name(experiment).experiment_id
    runs = [r for r in client.search_runs([eid]) if name is None or r.info.run_name == name]
    assert len(runs) == 1, [r.info.run_name for r in runs]
    return client, runs[0]


def _history(client, run_id: str) -> dict[str, list[tuple[int, float]]]:
    """Every metric's (step, value) pairs, each step logged once (run-level ``mean/*``
    figures once, at the last round: an interrupted run logs none)."""
    out = {}
    for key in client.get_run(run_id).data.metrics:
        history = client.get_metric_history(run_id, key)
        steps = [m.step for m in history]
        assert len(steps) == len(set(steps)), f"{key} logged twice at a step: {steps}"
        if not any(t in key for t in TIMING):
            out[key] = sorted((m.step, m.value) for m in history)
    return out


def _untimed(rows):
    return [{k: v for k, v in r.items() if not any(t in k for t in TIMING)} for r in rows]


def _same_as_reference(client, resumed: str, reference_store: str, reference: str) -> None:
    ref_client = mlflow.MlflowClient(reference_store)
    expected, found = _history(ref_client, reference), _history(client, resumed)
    assert len(found) > 50
    assert found == expected  # bitwise: same floats, same steps
    assert _untimed(results_csv(client, resumed)) == _untimed(results_csv(ref_client, reference))


def _logged(store: str, step: int):
    """True once some run of the store has wholly logged round ``step``."""

    def ready() -> bool:
        try:
            client = mlflow.MlflowClient(store)
            eid = client.get_experiment_by_name("fedlgr-debug").experiment_id
            runs = client.search_runs([eid])
        except Exception:  # the store or experiment is not there yet
            return False
        return any(
            step in {m.step for m in client.get_metric_history(r.info.run_id, "round/seconds")}
            for r in runs
        )

    return ready


# --------------------------------------------------------------------------- killed runs


@pytest.mark.slow
@pytest.mark.parametrize("extra", [FEDLGR, NR], ids=["fedlgr", "fedroot-nr"])
def test_a_killed_fcl_run_resumes_bit_for_bit_in_the_same_mlflow_run(
    synth_dir, cache_dir, tmp_path, extra
):
    """FedLGR (generator, labeller, frozen root statistics) and FedRoot-NR (the memory and
    its sampler), SIGKILLed after round 2 of 4."""
    reference = f"sqlite:///{tmp_path}/reference.db"
    result = run_experiment(fast_config(synth_dir, cache_dir, reference, *extra))
    store = f"sqlite:///{tmp_path}/mlflow.db"
    args = run_args(synth_dir, cache_dir, store, *extra)
    folder = _killed_after_checkpoint(args, tmp_path)
    client, run = _only_run(store)
    assert run.info.status == "RUNNING"  # killed: nobody ended it
    assert folder.name == run.info.run_id

    done = _finish([*args, "--resume"], tmp_path)
    assert f"resuming run {run.info.run_id} after round 2 of 4" in done.stdout
    client, resumed = _only_run(store)  # one run, the same one
    assert resumed.info.run_id == run.info.run_id and resumed.info.status == "FINISHED"
    _same_as_reference(client, run.info.run_id, reference, result.run_id)
    assert not folder.exists()  # a finished run keeps no checkpoint


@pytest.mark.slow
def test_a_killed_100_client_run_with_idle_clients_on_disk_resumes_bit_for_bit(cache_dir, tmp_path):
    """A cross-device run (issue 40): 100 clients, 10 a round, the idle ones' states in
    files (compact: the clients never woken have none), SIGKILLed after round 2 of 4;
    the checkpoint holds the woken clients' compact states and the resumed run computes
    what an uninterrupted one whose idle clients stayed whole computes."""
    data = tmp_path / "data"
    synthesize(data, scenes=200, seed=7, size=32)
    extra = [
        "method=FedRootAvg",
        "data.clients=100",
        "federated.fraction=0.1",
        "federated.rounds=4",
    ]
    reference = f"sqlite:///{tmp_path}/reference.db"
    result = run_experiment(
        fast_config(data, cache_dir, reference, *extra, "runtime.idle_clients=live")
    )
    store = f"sqlite:///{tmp_path}/mlflow.db"
    args = run_args(data, cache_dir, store, *extra, "runtime.idle_clients=disk")
    folder = _killed_after_checkpoint(args, tmp_path)
    state = ckpt.load(folder / "round-0002.ckpt")
    woken = state["clients"]
    assert 10 <= len(woken) <= 20  # those chosen in rounds 1 and 2, not the 100
    for kept in woken.values():  # the root is the global one: only its step counters
        assert all(not v.is_floating_point() for k, v in kept["model"].items() if "root." in k)
        assert any(k.startswith("top.") for k in kept["model"])
    done = _finish([*args, "--resume"], tmp_path)
    assert "after round 2 of 4" in done.stdout
    client, run = _only_run(store)
    _same_as_reference(client, run.info.run_id, reference, result.run_id)
    assert not list((tmp_path / "checkpoints").glob(".idle-clients-*"))


@pytest.mark.slow
def test_a_run_killed_after_logging_a_round_it_had_not_checkpointed_logs_it_once(
    synth_dir, cache_dir, tmp_path
):
    """FedOpt (the server's Adam moments are state) with a checkpoint every 2 rounds,
    killed once round 3 is logged: the resumed run redoes round 3 from the round-2
    checkpoint and does not log it again."""
    extra = ["method=FedOpt", "federated.rounds=4", "tracking.checkpoint=2"]
    reference = f"sqlite:///{tmp_path}/reference.db"
    result = run_experiment(
        fast_config(synth_dir, cache_dir, reference, *extra, "runtime.threads=1")
    )
    store = f"sqlite:///{tmp_path}/mlflow.db"
    args = run_args(synth_dir, cache_dir, store, *extra)
    process = _start(args, tmp_path)
    _kill_when(process, _logged(store, 3), "round 3 logged")
    client, run = _only_run(store)
    assert [p.name for p in ckpt.checkpoints(tmp_path / "checkpoints" / run.info.run_id)] == [
        "round-0002.ckpt"
    ]
    done = _finish([*args, "--resume", run.info.run_id], tmp_path)
    assert "after round 2 of 4" in done.stdout
    _same_as_reference(client, run.info.run_id, reference, result.run_id)


@pytest.mark.slow
@pytest.mark.parametrize(
    "extra",
    [
        NR,
        ["method=FedRootDistill", "federated.rounds=3"],
        # client-level DP: the releases so far (epsilon, the noise's draws) and the clip
        # norm adaptive clipping moved; half the clients, Poisson-sampled
        [
            "federated.rounds=3",
            "federated.fraction=0.5",
            "federated.dp.clip=0.5",
            "federated.dp.clipping=adaptive",
            "federated.dp.count_noise=1",
            "federated.dp.noise_multiplier=0.5",
            "federated.dp.delta=0.1",
        ],
    ],
    ids=["nr-memory", "distill-teacher", "dp-adaptive"],
)
def test_an_interrupted_run_resumes_with_its_plugin_state(synth_dir, cache_dir, tmp_path, extra):
    reference = f"sqlite:///{tmp_path}/reference.db"
    threads = "runtime.threads=1"
    expected = run_experiment(fast_config(synth_dir, cache_dir, reference, *extra, threads))
    store = f"sqlite:///{tmp_path}/mlflow.db"
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        *extra,
        "runtime.threads=1",
        f"tracking.checkpoint_dir={tmp_path / 'ckpt'}",
    )

    def stop(round_, metrics):
        if round_ == 2:
            raise Interrupt()

    with pytest.raises(Interrupt):
        run_experiment(config, on_round=stop)
    client, run = _only_run(store)
    assert run.info.status == "KILLED"
    assert ckpt.checkpoints(tmp_path / "ckpt" / run.info.run_id)[-1].name == "round-0002.ckpt"
    resumed = run_experiment(config, resume=run.info.run_id)
    assert resumed.run_id == run.info.run_id and len(resumed.rounds) == len(expected.rounds)
    _same_as_reference(client, run.info.run_id, reference, expected.run_id)
    for a, b in zip(resumed.rounds, expected.rounds, strict=True):
        mask = [not any(t in f.name for t in TIMING) for f in a.fields]
        # NaN where a client did not train (half of them each round)
        assert np.array_equal(a.table[:, mask], b.table[:, mask], equal_nan=True)
        assert a.server.get("privacy/epsilon") == b.server.get("privacy/epsilon")


@pytest.mark.slow
def test_a_killed_two_process_run_resumes_bit_for_bit(synth_dir, cache_dir, tmp_path):
    """Fabric DDP on CPU (gloo): every process's clients and RNGs come back."""
    extra = [*FEDLGR, "runtime.devices=2"]
    reference = f"sqlite:///{tmp_path}/reference.db"
    _finish([*run_args(synth_dir, cache_dir, reference, *extra)], tmp_path)
    _, expected = _only_run(reference)
    store = f"sqlite:///{tmp_path}/mlflow.db"
    args = run_args(synth_dir, cache_dir, store, *extra)
    folder = _killed_after_checkpoint(args, tmp_path)
    client, run = _only_run(store)
    assert folder.name == run.info.run_id
    state = ckpt.load(folder / "round-0002.ckpt")
    assert sorted(state["clients"]) == [0, 1] and len(state["rng"]) == 2  # both processes'
    done = _finish([*args, "--resume"], tmp_path)
    assert "2 processes" in done.stdout and "after round 2 of 4" in done.stdout
    _same_as_reference(client, run.info.run_id, reference, expected.info.run_id)


# --------------------------------------------------------------------------- refusals


@pytest.fixture
def interrupted(synth_dir, cache_dir, tmp_path):
    """A FedAvg run of 4 rounds stopped (Ctrl-C) after round 3: checkpoints of rounds 2
    and 3 (keep 2)."""
    store = f"sqlite:///{tmp_path}/mlflow.db"
    config = fast_config(synth_dir, cache_dir, store, "federated.rounds=4", "runtime.threads=1")

    def stop(round_, metrics):
        if round_ == 3:
            raise Interrupt()

    with pytest.raises(Interrupt):
        run_experiment(config, on_round=stop)
    _client, run = _only_run(store)
    folder = tmp_path / "checkpoints" / run.info.run_id
    assert [p.name for p in ckpt.checkpoints(folder)] == ["round-0002.ckpt", "round-0003.ckpt"]
    return config, run.info.run_id, folder


@pytest.mark.slow
def test_a_truncated_checkpoint_is_named_with_the_way_out(interrupted):
    config, run_id, folder = interrupted
    latest = folder / "round-0003.ckpt"
    latest.write_bytes(latest.read_bytes()[:5000])
    with pytest.raises(FedlgrError) as caught:
        run_experiment(config, resume=run_id)
    message = str(caught.value)
    assert str(latest) in message and "not a readable fedlgr checkpoint" in message
    assert "delete it to resume from the previous checkpoint" in message
    assert "weights_only=False" not in message
    latest.unlink()  # the way out it names
    result = run_experiment(config, resume=run_id)
    assert [r.round for r in result.rounds] == [1, 2, 3, 4]


@pytest.mark.slow
def test_a_write_cut_short_leaves_the_previous_checkpoint(interrupted):
    """A kill during a write leaves only the temporary file: never a checkpoint."""
    config, run_id, folder = interrupted
    (folder / "round-0003.ckpt").unlink()
    (folder / ".round-0003.ckpt.tmp").write_bytes(b"half a checkpoint")
    assert [p.name for p in ckpt.checkpoints(folder)] == ["round-0002.ckpt"]
    result = run_experiment(config, resume=run_id)
    assert [r.round for r in result.rounds] == [1, 2, 3, 4]
    assert mlflow.MlflowClient(config.tracking.uri).get_run(run_id).info.status == "FINISHED"
    finished = (
        rf"no unfinished run of this config in MLflow experiment .* \(run {run_id} has finished\)"
    )
    with pytest.raises(FedlgrError, match=finished):
        run_experiment(config, resume=True)


@pytest.mark.slow
def test_a_resume_with_other_settings_is_refused_by_name(interrupted, synth_dir, cache_dir):
    config, run_id, _folder = interrupted
    store = config.tracking.uri
    changed = fast_config(
        synth_dir, cache_dir, store, "federated.rounds=4", "runtime.threads=1", "train.lr_top=0.5"
    )
    with pytest.raises(FedlgrError, match=r"train\.lr_top \(checkpoint 0\.001, now 0\.5\)"):
        run_experiment(changed, resume=run_id)
    with pytest.raises(FedlgrError, match="no unfinished run of this config"):
        run_experiment(changed, resume=True)  # another config: not this run
    safe = fast_config(
        synth_dir,
        cache_dir,
        store,
        "federated.rounds=4",
        "runtime.threads=1",
        "runtime.progress=true",
        "tracking.keep_checkpoints=1",
    )
    result = run_experiment(safe, resume=True)  # the latest unfinished run of this config
    assert result.run_id == run_id and len(result.rounds) == 4
    with pytest.raises(FedlgrError, match=f"run {run_id} has finished"):
        run_experiment(config, resume=run_id)


@pytest.mark.slow
def test_a_live_run_is_not_resumed_and_an_unknown_one_is_named(interrupted):
    config, run_id, _folder = interrupted
    client = mlflow.MlflowClient(config.tracking.uri)
    client.update_run(run_id, status="RUNNING")
    client.set_tag(run_id, "fedlgr.pid", str(os.getpid()))  # this very process: alive
    client.set_tag(run_id, "fedlgr.heartbeat", f"{time.time():.0f}")
    with pytest.raises(FedlgrError, match=f"run {run_id} is still running"):
        run_experiment(config, resume=run_id)
    with pytest.raises(FedlgrError, match="--resume 0123abc: no such run"):
        run_experiment(config, resume="0123abc")
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    client.set_tag(run_id, "fedlgr.pid", str(gone.pid))  # dead: marked KILLED, then resumed
    result = run_experiment(config, resume=run_id)
    assert len(result.rounds) == 4
    run = client.get_run(run_id)
    assert run.info.status == "FINISHED"
    assert run.data.tags["fedlgr.ended"].startswith(f"marked KILLED: its process {gone.pid}")


@pytest.mark.slow
def test_checkpoint_files_hold_only_tensors_and_plain_values(interrupted):
    _config, run_id, folder = interrupted
    state = torch.load(folder / "round-0002.ckpt", weights_only=True)  # no pickled code
    assert state["format"] == ckpt.FORMAT and state["run_id"] == run_id and state["round"] == 2
    assert state["config"]["federated.rounds"] == "4"
    assert [r["round"] for r in state["rows"]] == [1, 2]
    assert set(state["clients"]) == {0, 1}
    assert set(state["clients"][0]) >= {"model", "optimizer", "plugins", "batches_rng"}


@pytest.mark.slow
def test_a_report_marks_a_dead_run_killed(tmp_path):
    from fedlgr.shell.report.runs import ReportError, select_runs

    store = f"sqlite:///{tmp_path}/mlflow.db"
    client = mlflow.MlflowClient(store)
    eid = client.create_experiment("e")
    tags = {
        "method": "FedAvg",
        "benchmark": "FL",
        "clients": "2",
        "fedlgr.host": os.uname().nodename,
    }
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = client.create_run(eid, tags={**tags, "fedlgr.pid": str(gone.pid)}).info.run_id
    live = client.create_run(eid, tags={**tags, "fedlgr.pid": str(os.getpid())}).info.run_id
    for run_id in (dead, live):
        client.set_tag(run_id, "fedlgr.heartbeat", f"{time.time():.0f}")
    with pytest.raises(ReportError, match=r"other runs: 1 RUNNING, 1 KILLED|1 KILLED, 1 RUNNING"):
        select_runs(client, store, experiment="e")
    assert client.get_run(dead).info.status == "KILLED"
    assert client.get_run(live).info.status == "RUNNING"


@pytest.mark.slow
def test_the_effective_thread_count_is_a_param_and_part_of_the_config(
    synth_dir, cache_dir, tmp_path
):
    """Results depend on it (floating-point order), so a run records it, not None."""
    store = f"sqlite:///{tmp_path}/mlflow.db"
    config = fast_config(synth_dir, cache_dir, store, "runtime.threads=null")
    result = run_experiment(config)
    params = mlflow.MlflowClient(store).get_run(result.run_id).data.params
    assert params["runtime.threads"] == str(torch.get_num_threads()) != "None"
    assert result.config.runtime.threads == torch.get_num_threads()


WRITER = """
import sys, torch
from pathlib import Path
from lightning.fabric import Fabric
from fedlgr.shell.run import checkpoint as ckpt
fabric = Fabric(accelerator="cpu", devices=1)
state = {"format": ckpt.FORMAT, "run_id": "r", "big": torch.randn(12_000_000)}
for round_ in range(1, 1000):
    ckpt.save(fabric, Path(sys.argv[1]), round_, {**state, "round": round_}, keep=2)
"""


@pytest.mark.slow
def test_a_kill_during_a_write_leaves_whole_checkpoints_only(tmp_path):
    """A real process writing 48 MB checkpoints in a loop, killed in the middle of one:
    every file that looks like a checkpoint loads, and the newest is resumable."""
    folder = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(folder)], env=env)
    deadline = time.monotonic() + 120
    while len(ckpt.checkpoints(folder)) < 2 or not list(folder.glob(".*.tmp")):
        assert writer.poll() is None and time.monotonic() < deadline
        time.sleep(0.01)
    writer.kill()  # a temporary file exists: the kill lands in (or right after) a write
    writer.wait()
    found = ckpt.checkpoints(folder)
    assert 1 <= len(found) <= 2
    rounds = [ckpt.load(p)["round"] for p in found]  # every one whole
    assert rounds == sorted(rounds) and found[-1].name == f"round-{rounds[-1]:04d}.ckpt"


@pytest.mark.slow
def test_a_resume_takes_the_run_s_own_thread_settings_where_left_to_the_machine(
    synth_dir, cache_dir, tmp_path
):
    """The default thread count follows the machine's load (and concurrency follows it): a
    resume that leaves them unset takes the checkpoint's, one that sets others is refused."""
    from fedlgr.shell.run.resume import MACHINE_CHOSEN, Resumed, adopted, load_checkpoint

    store = f"sqlite:///{tmp_path}/mlflow.db"
    chosen = ["federated.rounds=3", "runtime.threads=2", "runtime.concurrency=threads"]
    started = []

    def stop_in_round_3(round_, metrics):
        if round_ == 3:
            raise RuntimeError("stopped")

    with pytest.raises(RuntimeError, match="stopped"):
        run_experiment(
            fast_config(synth_dir, cache_dir, store, *chosen),
            on_start=started.append,
            on_round=stop_in_round_3,
        )
    run_id = started[0]
    tags = mlflow.MlflowClient(store).get_run(run_id).data.tags
    path = ckpt.checkpoints(Path(tags["fedlgr.checkpoints"]))[-1]
    # This machine, busier now, would choose one thread and sequential training.
    now = fast_config(
        synth_dir, cache_dir, store, "federated.rounds=3", "runtime.concurrency=sequential"
    )
    with pytest.raises(FedlgrError, match=r"runtime\.threads \(checkpoint 2, now 1\)"):
        load_checkpoint(now, run_id, path)
    state = load_checkpoint(now, run_id, path, frozenset(MACHINE_CHOSEN))
    resumed = Resumed(run_id, state, path.parent)
    own = adopted(resumed, frozenset(MACHINE_CHOSEN))
    assert own == {"threads": 2, "concurrency": "threads", "workers": 2}
    assert adopted(resumed, frozenset()) == {}


@pytest.mark.slow
def test_a_run_resumed_without_checkpoints_removes_its_old_folder_when_it_finishes(interrupted):
    """Found by the re-test of the third sweep: `--resume tracking.checkpoint=0` finished
    the run and left its old checkpoints and lock behind."""
    import dataclasses

    config, run_id, folder = interrupted
    config = dataclasses.replace(
        config, tracking=dataclasses.replace(config.tracking, checkpoint=0)
    )
    result = run_experiment(config, resume=run_id)
    assert [r.round for r in result.rounds] == [1, 2, 3, 4]
    assert not folder.exists()


@pytest.mark.slow
def test_a_checkpoint_folder_the_user_made_is_kept_when_a_run_finishes(
    tmp_path, synth_dir, cache_dir
):
    """The tenth fault sweep: a finished run removed an empty tracking.checkpoint_dir the
    user had made (d196), and the folder a link there led to, leaving the link leading
    nowhere (d190). fedlgr's own checkpoints/ beside the store still goes."""
    mine, real = tmp_path / "mine", tmp_path / "real"
    mine.mkdir()
    real.mkdir()
    (tmp_path / "link").symlink_to(real)
    base = ["run", "debug/tiny", f"data.path={synth_dir}", f"data.cache_dir={cache_dir}"]
    for folder in (mine, tmp_path / "link"):
        store = f"sqlite:///{tmp_path / 'mlflow.db'}"
        assert main([*base, f"tracking.checkpoint_dir={folder}", "--tracking-uri", store]) == 0
        assert folder.is_dir() and not any(folder.iterdir())
    assert main([*base, "--tracking-uri", f"sqlite:///{tmp_path / 'own' / 'mlflow.db'}"]) == 0
    assert "checkpoints" not in {p.name for p in (tmp_path / "own").iterdir()}


@pytest.mark.slow
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_sigterm_ends_the_run_killed_with_its_rounds_and_resume_finishes_it(
    synth_dir, cache_dir, tmp_path, monkeypatch, capsys
):
    """SIGTERM (timeout, Slurm, docker stop) is handled like Ctrl-C: exit 143 (128 + 15)
    at once, the MLflow run KILLED (not left RUNNING) with results.csv of the rounds done;
    ``fedlgr run --resume`` then finishes that same run, every round logged once."""
    store = f"sqlite:///{tmp_path}/mlflow.db"
    rounds = 12
    args = run_args(synth_dir, cache_dir, store, f"federated.rounds={rounds}")
    with Child(args, tmp_path, "terminated") as child:
        # Printed once round 1 is logged (step 1 of round/seconds) and checkpointed; the
        # signal goes at once, as later rounds take a fraction of a second each.
        child.wait_for(rf"round 1/{rounds}:")
        code, took = child.signal_and_wait(signal.SIGTERM)
        stderr = child.stderr()
    assert code == 128 + signal.SIGTERM, stderr[-3000:]
    assert took < 10, f"{took:.1f} s from SIGTERM to exit"
    assert "fedlgr: terminated (SIGTERM)" in stderr, stderr[-3000:]
    assert "Traceback" not in stderr, stderr[-3000:]

    client, run = only_run(store)
    run_id = run.info.run_id
    assert run.data.tags["fedlgr.pid"] == str(child.pid)
    assert run.info.status == "KILLED"
    logged = metric_steps(client, run_id)
    assert logged == list(range(1, len(logged) + 1)) and 1 <= len(logged) < rounds
    kept = csv_rounds(results_csv(client, run_id))
    assert sorted(kept) == list(range(1, len(kept) + 1))
    assert len(kept) in (len(logged), len(logged) + 1)  # the signal may fall between the two
    assert all(clients == ["0", "1"] for clients in kept.values())
    # Its summary so far is its description, not mean/* metrics a resume cannot take back.
    assert not [key for key in run.data.metrics if key.startswith("mean/")]
    note = run.data.tags["mlflow.note.content"]
    assert note.startswith(f"**{run.info.run_name}: KILLED after {len(kept)} of {rounds} rounds")
    assert "CPU s/round" in note

    monkeypatch.chdir(tmp_path)
    assert main(["run", *args, "--resume"]) == 0
    said = capsys.readouterr().out
    assert re.search(rf"resuming run {run_id} after round \d+ of {rounds}", said), said
    client, run = only_run(store)
    assert run.info.run_id == run_id and run.info.status == "FINISHED"
    assert metric_steps(client, run_id) == list(range(1, rounds + 1))  # each round once
    done = csv_rounds(results_csv(client, run_id))
    assert sorted(done) == list(range(1, rounds + 1))
    assert all(clients == ["0", "1"] for clients in done.values())
    assert not Path(run.data.tags["fedlgr.checkpoints"]).exists()  # a finished run has none
    _one_summary_of_the_whole_run(client, run, rounds)


def _one_summary_of_the_whole_run(client, run, rounds: int) -> None:
    """Issue 37's tester (Deliver 7): after SIGTERM and --resume the killed attempt's
    ``mean/*`` points stayed beside the final ones (two points in ``mean/cost/cpu_s``'s
    history). Each ``mean/*`` has one point, at the last round, the mean over every
    round's clients (results.csv) or every round (the server's figures)."""
    run_id = run.info.run_id
    rows = results_csv(client, run_id)
    means = {k: v for k, v in run.data.metrics.items() if k.startswith("mean/")}
    assert {"mean/cost/cpu_s", "mean/cost/bytes_up"} <= set(means), sorted(means)
    for key, value in means.items():
        history = [(m.step, m.value) for m in client.get_metric_history(run_id, key)]
        assert history == [(rounds, value)], key
        figure = key.removeprefix("mean/")
        name = figure.replace("/", "_")  # its results.csv column
        if figure == "cost/paper_cpu_s":  # the server's CPU over clients x rounds
            per_round = [m.value for m in client.get_metric_history(run_id, "cost/server_cpu_s")]
            expected = sum(per_round) / (2 * rounds)
        elif name in rows[0]:
            column = [float(r[name]) for r in rows if r[name]]
            assert len(column) == 2 * rounds, key
            expected = sum(column) / len(column)
        else:
            per_round = [m.value for m in client.get_metric_history(run_id, figure)]
            assert len(per_round) == rounds, key
            expected = sum(per_round) / rounds
        # numpy's pairwise sum and Python's running sum of at most 24 doubles of one sign
        # differ by a few dozen ulp of the total at most: well inside 1e-13
        assert value == pytest.approx(expected, rel=1e-13, abs=0), key


@pytest.mark.slow
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_ctrl_c_while_a_checkpoint_is_written_is_an_interrupt_not_a_full_disk(
    synth_dir, cache_dir, tmp_path, monkeypatch, capsys
):
    """Issue 37, Deliver 7: Ctrl-C while round 2's checkpoint was written was reported as
    "cannot write checkpoint ... free space" and ended the run FAILED - torch.save wraps
    the KeyboardInterrupt raised in one of its writes in a RuntimeError. It is an
    interrupt: exit 130, the run KILLED, the partial file gone, round 1's checkpoint
    intact, and --resume finishes the run."""
    store = f"sqlite:///{tmp_path}/mlflow.db"
    args = run_args(synth_dir, cache_dir, store, "federated.rounds=3", *BIG_CHECKPOINT)
    with Child(args, tmp_path, "checkpoint") as child:
        writing = ".round-0002.ckpt.tmp"  # round 1's checkpoint is on disk
        partial = partial_checkpoint(tmp_path / "checkpoints", child.process, writing)
        code, _ = child.signal_and_wait(signal.SIGINT)
        stderr = child.stderr()
    client, run = only_run(store)
    run_id = run.info.run_id
    assert code == 130, stderr[-3000:]
    assert "free space" not in stderr and "Traceback" not in stderr, stderr[-3000:]
    assert stderr.strip().splitlines()[-1] == (
        f"fedlgr: interrupted; MLflow run {run_id} ended KILLED; "
        f"the same command with --resume {run_id} continues it"
    )
    assert run.info.status == "KILLED"
    assert sorted(p.name for p in partial.parent.glob("*.ckpt*")) == ["round-0001.ckpt"]
    assert not partial.exists()

    monkeypatch.chdir(tmp_path)
    assert main(["run", *args, "--resume"]) == 0
    assert f"resuming run {run_id} after round 1 of 3" in capsys.readouterr().out
    client, run = only_run(store)
    assert run.info.status == "FINISHED" and metric_steps(client, run_id) == [1, 2, 3]
