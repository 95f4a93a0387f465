"""One owner per run, resume only on the run's own data, checkpoints that leave nothing
behind, a rendezvous that ends, and stores that fail in one line (issue 20, points 1, 4,
5, 7 and the store cases of 8): real processes, real signals, real sqlite stores. A run
left RUNNING by a dead process is found by its tags and marked KILLED."""

from __future__ import annotations

import contextlib
import os
import re
import resource
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest

from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.stores import TrackingUnreachable, check_sqlite_usable
from fedlgr.shell.cli import main
from fedlgr.shell.config import load_config
from fedlgr.shell.data.synth import synthesize
from fedlgr.shell.report.runs import select_runs
from fedlgr.shell.run import checkpoint as ckpt
from fedlgr.shell.run.resume import find_checkpoint
from fedlgr.shell.tracking.liveness import dead_reason, end_dead_runs
from fedlgr.shell.tracking.mlflow_run import SENTINEL
from fedlgr.shell.tracking.store import StoreError
from tests.support.ports import free_port
from tests.support.processes import Child, child_env, metric_steps, only_run, run_args
from tests.support.runs import fast_config

REPO = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- 1 and 4


@pytest.mark.slow
def test_a_run_has_one_owner_and_resumes_only_on_its_own_data(
    synth_dir, cache_dir, tmp_path, monkeypatch, capsys
):
    """(1b) A run whose process is stopped (Ctrl-Z) and whose heartbeat went stale is
    alive, not dead: ``--resume`` is refused naming its owner. (4) Killed, and its data
    regenerated, ``--resume`` is refused naming both digests. (1a) Two ``--resume`` at
    once: one resumes, the other is refused; every round is logged once, and the old
    checkpoint folder is gone after the move to a new one (7)."""
    data = tmp_path / "data"
    shutil.copytree(synth_dir, data)
    store = f"sqlite:///{tmp_path}/mlflow.db"
    rounds = 10
    args = run_args(data, cache_dir, store, f"federated.rounds={rounds}", "tracking.heartbeat_s=1")
    monkeypatch.chdir(tmp_path)
    with Child(args, tmp_path, "first") as child:
        child.wait_for(rf"round 2/{rounds}:")
        os.kill(child.pid, signal.SIGSTOP)
        try:
            time.sleep(4)  # more than 3 heartbeats of 1 s
            client, run = only_run(store)
            run_id = run.info.run_id
            assert time.time() - float(run.data.tags["fedlgr.heartbeat"]) > 3
            assert dead_reason(run) is None  # its process is alive on this machine
            assert main(["run", *args, "--resume"]) == 1
            said = capsys.readouterr().err
            assert f"run {run_id} is owned by process {child.pid} on {socket.gethostname()}" in (
                said
            ), said
            assert client.get_run(run_id).info.status == "RUNNING"
        finally:
            os.kill(child.pid, signal.SIGKILL)
        child.process.wait()
    old_folder = Path(client.get_run(run_id).data.tags["fedlgr.checkpoints"])
    assert ckpt.checkpoints(old_folder)

    kept = tmp_path / "kept"
    shutil.copytree(data, kept)
    shutil.rmtree(data)
    synthesize(data, scenes=48, seed=8, size=32)  # other scenes in the same folder
    assert main(["run", *args, "--resume"]) == 1
    said = capsys.readouterr().err.strip()
    assert len(said.splitlines()) == 1, said
    assert re.search(
        rf"data.path={re.escape(str(data))} is not the data run {run_id} trained on "
        r"\(dataset digest [0-9a-f]{16}, the checkpoint's [0-9a-f]{16}\)",
        said,
    ), said
    shutil.rmtree(data)
    shutil.copytree(kept, data)  # the run's own data again: the same digest

    moved = tmp_path / "moved"
    again = [*args, f"tracking.checkpoint_dir={moved}", "--resume"]
    with Child(again, tmp_path, "a") as a, Child(again, tmp_path, "b") as b:
        codes = [a.process.wait(timeout=300), b.process.wait(timeout=300)]
        errors = [a.stderr(), b.stderr()]
    assert sorted(codes) == [0, 1], errors
    refused = errors[codes.index(1)].strip().splitlines()[-1]
    assert re.search(rf"run {run_id} (is owned by process \d+|has finished)", refused), refused
    client, run = only_run(store)
    assert run.info.status == "FINISHED"
    for key in (SENTINEL, "test/rmse", "cost/cpu_s"):
        assert metric_steps(client, run_id, key) == list(range(1, rounds + 1)), key  # each once
    assert not old_folder.exists()  # moved, then finished: neither folder is left
    assert not (moved / run_id).exists()


# --------------------------------------------------------------------------- 7


@pytest.mark.slow
def test_a_finished_runs_leftover_checkpoints_are_removed_by_resume_and_report(
    synth_dir, cache_dir, tmp_path, capsys
):
    """A kill just after a run FINISHED leaves its checkpoint folder: ``--resume`` and
    ``fedlgr report`` remove it, with a line."""
    store = f"sqlite:///{tmp_path}/mlflow.db"
    config = fast_config(synth_dir, cache_dir, store)
    client = mlflow.MlflowClient(store)
    experiment = client.create_experiment(config.tracking.experiment)
    folder = tmp_path / "checkpoints" / "left"
    run_id = client.create_run(experiment, tags={"fedlgr.checkpoints": str(folder)}).info.run_id
    client.set_terminated(run_id, "FINISHED")

    def leave() -> None:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "round-0003.ckpt").write_bytes(b"\0" * 3 * 2**20)

    leave()
    with pytest.raises(FedlgrError) as refused:
        find_checkpoint(config, run_id, client)
    assert str(refused.value) == (
        f"--resume: run {run_id} has finished; there is nothing to resume (removed the "
        f"checkpoint folder it left behind, {folder}: 3 MiB)"
    )
    assert not folder.exists()
    leave()
    with pytest.raises(FedlgrError, match="has no finished fedlgr runs"):  # not one of ours
        select_runs(client, store, experiment=config.tracking.experiment)
    said = capsys.readouterr().out
    assert f"finished run {run_id}: removed the checkpoint folder it left behind, {folder}" in said
    assert not folder.exists()


@contextlib.contextmanager
def _file_size_limit(limit: int):
    """A full disk, for this process: writes past ``limit`` bytes of a file fail with
    EFBIG (SIGXFSZ ignored) until the block ends."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)


def test_a_checkpoint_is_written_in_its_folder_and_a_failed_write_leaves_nothing(
    tmp_path, monkeypatch
):
    """Checkpoints are staged in their own folder, not ``$TMPDIR`` (a kill left 20-30 MB
    there); a write that fails (full disk; here a file-size limit) is one line, the
    previous checkpoint is intact and no temporary is left; stale temporaries of a kill
    are removed at the next start."""
    import tempfile

    import torch
    from lightning.fabric import Fabric

    folder, tmp = tmp_path / "run", tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))
    monkeypatch.setattr(tempfile, "tempdir", None)  # re-read $TMPDIR
    fabric = Fabric(accelerator="cpu", devices=1)
    ckpt.save(fabric, folder, 1, {"format": ckpt.FORMAT, "w": torch.zeros(1000)}, keep=2)
    with _file_size_limit(200_000), pytest.raises(FedlgrError) as refused:
        ckpt.save(fabric, folder, 2, {"format": ckpt.FORMAT, "w": torch.zeros(10**6)}, keep=2)
    assert str(refused.value).startswith(
        f"cannot write checkpoint {folder}/round-0002.ckpt: File too large; free "
        "space or choose another folder (tracking.checkpoint_dir=...)"
    ), refused.value
    assert sorted(p.name for p in folder.iterdir()) == ["round-0001.ckpt"]
    assert list(tmp.iterdir()) == []
    assert ckpt.load(folder / "round-0001.ckpt")["w"].shape == (1000,)

    stale = folder / ".round-0002.ckpt.tmp"
    stale.write_bytes(b"cut short")
    assert ckpt.remove_temporaries(folder) == [stale]
    assert sorted(p.name for p in folder.iterdir()) == ["round-0001.ckpt"]


def test_a_checkpoint_without_its_run_is_refused_in_one_line(tmp_path):
    path = tmp_path / "round-0001.ckpt"
    import torch

    torch.save({"format": ckpt.FORMAT}, path)
    with pytest.raises(FedlgrError, match=r"an incomplete checkpoint \(no run_id, round, "):
        ckpt.load(path, ckpt.RUN_KEYS)


# --------------------------------------------------------------------------- 5


@pytest.mark.slow
def test_a_rendezvous_without_its_peers_ends_on_sigterm_and_on_its_timeout(
    synth_dir, cache_dir, tmp_path
):
    """``runtime.num_nodes=2`` with no second node: SIGTERM ends the waiting process at
    once (it blocks in C++, where Python's handlers never run), and
    ``runtime.timeout_s`` ends the wait with one line."""
    store = f"sqlite:///{tmp_path}/mlflow.db"

    def start(timeout: float, name: str) -> tuple[subprocess.Popen, Path]:
        args = run_args(
            synth_dir, cache_dir, store, "runtime.num_nodes=2", f"runtime.timeout_s={timeout}"
        )
        err = tmp_path / f"{name}.stderr"
        env = child_env(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(free_port()), NODE_RANK="0")
        process = subprocess.Popen(
            [sys.executable, "-m", "fedlgr", "run", *args],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=err.open("w"),
            start_new_session=True,
        )
        return process, err

    waiting, err = start(600, "waiting")
    alone, alone_err = start(2, "alone")  # side by side: two start-ups cost one
    try:
        deadline = time.monotonic() + 120
        while "MEMBER: 1/2" not in err.read_text():
            assert waiting.poll() is None and time.monotonic() < deadline, err.read_text()
            time.sleep(0.2)
        time.sleep(1)  # inside the rendezvous
        os.kill(waiting.pid, signal.SIGTERM)
        assert waiting.wait(timeout=10) == -signal.SIGTERM
        assert alone.wait(timeout=120) == 1
    finally:
        for process in (waiting, alone):
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
    err = alone_err
    last = err.read_text().strip().splitlines()[-1]
    assert re.fullmatch(
        r"fedlgr: error: runtime.num_nodes=2, runtime.devices=1: not every process joined "
        r"within runtime.timeout_s=2 s at 127.0.0.1:\d+ \(.*1/2 clients joined.*\); start "
        r"the other nodes' processes .*",
        last,
    ), err.read_text()[-3000:]
    assert "Traceback" not in err.read_text()


# --------------------------------------------------------------------------- 8: stores


def test_stores_that_cannot_be_used_are_one_line_before_any_work(
    synth_dir, cache_dir, tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "folder.db").mkdir()
    (tmp_path / "text.db").write_text("not a database\n")
    good = sqlite3.connect(tmp_path / "good.db")
    good.execute("create table t (x)")
    good.executemany("insert into t values (?)", [("x" * 100,)] * 2000)  # ~50 pages
    good.commit()
    good.close()
    whole = (tmp_path / "good.db").read_bytes()
    (tmp_path / "damaged.db").write_bytes(whole[:100] + b"\xff" * (len(whole) - 100))
    inner = bytearray(whole)
    inner[5 * 4096 : 9 * 4096] = b"\xff" * (4 * 4096)  # pages the schema does not read
    (tmp_path / "inner.db").write_bytes(bytes(inner))
    (tmp_path / "a-file").write_text("")
    cases = {
        f"sqlite:///{tmp_path}/folder.db": "is a folder; name the database file in it",
        f"sqlite:///{tmp_path}/text.db": "is not an SQLite database",
        f"sqlite:///{tmp_path}/damaged.db": "is damaged (database disk image is malformed)",
        f"sqlite:///{tmp_path}/inner.db": "is damaged (database disk image is malformed",
        f"sqlite:///{tmp_path}/a-file/mlflow.db": (
            f"is under {tmp_path}/a-file, a file, not a folder"
        ),
        f"file://{tmp_path}/mlruns": "a plain file store, which MLflow 3 keeps in maintenance",
        str(tmp_path / "mlruns"): "a plain file store",
    }
    for uri, why in cases.items():
        # A run through the CLI: refused before the data is loaded or a run is created.
        args = run_args(synth_dir, cache_dir, uri, "federated.rounds=1")
        assert main(["run", *args]) == 1, uri
        said = capsys.readouterr().err.strip()
        assert len(said.splitlines()) == 1 and why in said and uri in said, said

    locked = f"sqlite:///{tmp_path}/locked.db"
    holder = sqlite3.connect(tmp_path / "locked.db", check_same_thread=False)
    holder.execute("create table t (x)")
    holder.commit()
    holder.execute("BEGIN EXCLUSIVE")
    try:
        with pytest.raises(TrackingUnreachable, match="another process has kept it locked"):
            check_sqlite_usable(locked, wait=0.5)
    finally:
        holder.rollback()
        holder.close()
    check_sqlite_usable(locked, wait=0.5)  # free again


@pytest.mark.slow
def test_a_full_store_is_one_line_and_the_run_ends_failed_once_it_has_room(tmp_path, capfd):
    from fedlgr.shell.config import load_config
    from fedlgr.shell.tracking.mlflow_run import Tracker

    store = f"sqlite:///{tmp_path}/mlflow.db"
    config = load_config(None, [f"tracking.uri={store}", "tracking.system_metrics=false"])
    tracker = Tracker(config)
    size = (tmp_path / "mlflow.db").stat().st_size
    with _file_size_limit(size), pytest.raises(StoreError) as refused:
        for round_ in range(1, 200):
            tracker.log_round(round_, {f"m/{i}": float(i) for i in range(1000)})
    assert re.fullmatch(
        rf"MLflow store {re.escape(store)}: could not log round \(run {tracker.run_id}\): .+",
        str(refused.value),
    ), refused.value
    tracker.fail()
    assert mlflow.MlflowClient(store).get_run(tracker.run_id).info.status == "FAILED"
    assert "Traceback" not in capfd.readouterr().err  # MLflow's own log of it: one line


def test_store_errors_name_the_store_and_the_innermost_cause():
    from fedlgr.shell.tracking.mlflow_run import store_errors

    def fail() -> None:
        try:
            raise sqlite3.OperationalError("database or disk is full")
        except sqlite3.OperationalError as inner:
            raise RuntimeError("(sqlite3.OperationalError) wrapped\nmore") from inner

    with pytest.raises(StoreError) as err, store_errors("sqlite:///x.db", "log round"):
        fail()
    assert str(err.value) == (
        "MLflow store sqlite:///x.db: could not log round: database or disk is full"
    )


def test_a_sigterm_that_lands_in_a_finaliser_is_not_lost():
    """Found by the re-test: a SIGTERM whose handler ran inside a weakref callback of the
    garbage collector was printed ("Exception ignored in ...") and dropped, and the sweep
    went on for minutes. It is delivered again once the finaliser is done."""
    from fedlgr.shell.signals import Terminated, terminate_as_interrupt

    class Finalised:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)
            deadline = time.monotonic() + 0.2
            while time.monotonic() < deadline:  # the handler runs here, inside __del__
                pass

    with pytest.raises(Terminated), terminate_as_interrupt():
        thing = Finalised()
        del thing
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            time.sleep(0.01)
        pytest.fail("SIGTERM was lost")


def test_an_interrupt_while_a_run_is_being_started_ends_it_killed(tmp_path, synth_dir, monkeypatch):
    """The tenth fault sweep (d07, d155): Ctrl-C or SIGHUP 0.1 s into a sweep's trial, while
    its MLflow run was being set up, ended the run FAILED, as an error would; an interrupt
    later in the run ends it KILLED."""
    import mlflow

    from fedlgr.shell.tracking import mlflow_run

    def interrupted(*_args, **_kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(mlflow_run.context, "log_dataset", interrupted)
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    config = load_config(None, [f"data.path={synth_dir}", f"tracking.uri={store}"])
    with pytest.raises(KeyboardInterrupt):
        mlflow_run.Tracker(config)
    client = mlflow.MlflowClient(store)
    experiments = [e.experiment_id for e in client.search_experiments()]
    (run,) = client.search_runs(experiments)
    assert run.info.status == "KILLED"


def _gone_pid() -> int:
    """The pid of a process that has ended and been reaped."""
    process = subprocess.Popen(["true"])
    process.wait()
    return process.pid


@pytest.mark.slow
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_dead_running_runs_are_named_and_marked_killed_and_live_ones_left(tmp_path):
    store = f"sqlite:///{tmp_path}/mlflow.db"
    client = mlflow.MlflowClient(store)
    experiment = client.create_experiment("dead-runs")
    here, now = socket.gethostname(), time.time()

    def running(name: str, host: str, pid: int, beat: float | None):
        tags = {"fedlgr.host": host, "fedlgr.pid": str(pid), "fedlgr.heartbeat_s": "30.0"}
        if beat is not None:
            tags["fedlgr.heartbeat"] = f"{beat:.0f}"
        return client.create_run(experiment, run_name=name, tags=tags).info.run_id

    gone = _gone_pid()
    ids = {
        "gone": running("gone", here, gone, now),  # fresh heartbeat, but no process
        "live": running("live", here, os.getpid(), now),
        "stale-remote": running("stale-remote", "elsewhere.invalid", 1, now - 1000),
        "fresh-remote": running("fresh-remote", "elsewhere.invalid", 1, now),
        "no-heartbeat": running("no-heartbeat", here, gone, None),  # sweep parent, old fedlgr
        "finished": running("finished", here, gone, now - 1000),
    }
    client.set_terminated(ids["finished"], "FINISHED")

    reasons = {name: dead_reason(client.get_run(i)) for name, i in ids.items()}
    assert reasons["gone"] is not None
    assert str(gone) in reasons["gone"] and "gone" in reasons["gone"]
    assert reasons["stale-remote"] is not None and "heartbeat" in reasons["stale-remote"]
    for name in ("live", "fresh-remote", "no-heartbeat", "finished"):
        assert reasons[name] is None, (name, reasons[name])

    ended = end_dead_runs(client, [experiment])
    assert sorted(ended) == sorted([ids["gone"], ids["stale-remote"]])
    for name, run_id in ids.items():
        run = client.get_run(run_id)
        if name in ("gone", "stale-remote"):
            assert run.info.status == "KILLED"
            # the reason as dead_reason gives it (a heartbeat's age may have grown by a second)
            reason = re.sub(r"\d+ s \(", "N s (", reasons[name])
            assert re.sub(r"\d+ s \(", "N s (", run.data.tags["fedlgr.ended"]) == (
                f"marked KILLED: {reason}"
            )
        else:
            assert run.info.status == ("FINISHED" if name == "finished" else "RUNNING"), name
            assert "fedlgr.ended" not in run.data.tags, name
    assert end_dead_runs(client, [experiment]) == []  # nothing left to mark


@pytest.mark.slow
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_a_sigkilled_run_stays_running_until_it_is_found_dead(synth_dir, cache_dir, tmp_path):
    """SIGKILL runs no clean-up: the run stays RUNNING. Its tags name the process, so
    ``dead_reason`` sees it gone (already while it is an unreaped zombie) and
    ``end_dead_runs`` marks it KILLED."""
    store = f"sqlite:///{tmp_path}/mlflow.db"
    args = run_args(synth_dir, cache_dir, store, "federated.rounds=500")  # killed long before
    with Child(args, tmp_path, "sigkilled") as child:
        child.wait_for(r"round 1/500:")
        client, run = only_run(store)
        tags = run.data.tags
        assert tags["fedlgr.pid"] == str(child.pid)
        assert tags["fedlgr.host"] == socket.gethostname()
        assert abs(time.time() - float(tags["fedlgr.heartbeat"])) < 120
        assert run.info.status == "RUNNING" and dead_reason(run) is None  # alive
        os.kill(child.pid, signal.SIGKILL)
        deadline = time.monotonic() + 10
        while (reason := dead_reason(client.get_run(run.info.run_id))) is None:
            assert time.monotonic() < deadline, "the killed process still looks alive"
            time.sleep(0.05)
        assert child.process.wait(timeout=30) == -signal.SIGKILL
    assert f"process {child.pid} " in reason
    run = client.get_run(run.info.run_id)
    assert run.info.status == "RUNNING"  # nothing of the run's own cleaned up
    assert end_dead_runs(client, [run.info.experiment_id]) == [run.info.run_id]
    run = client.get_run(run.info.run_id)
    assert run.info.status == "KILLED"
    assert run.data.tags["fedlgr.ended"].startswith("marked KILLED: ")
    assert str(child.pid) in run.data.tags["fedlgr.ended"]
