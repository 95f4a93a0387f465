"""``fedlgr run`` as a real child process: its command line on the test data, its
environment, the process itself with its output as it comes, and the one run it left in a
store."""

from __future__ import annotations

import contextlib
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import mlflow

from fedlgr.shell.tracking.mlflow_run import SENTINEL

from .checkout import REPO
from .runs import FAST

TELEMETRY = "MLFLOW_DISABLE_TELEMETRY"
EXPERIMENT = "fedlgr-debug"  # conf/debug/fast.yaml's
# Every per-client and per-action metric in MLflow too: all of them are compared bit for bit.
DETAIL = "tracking.detail_metrics=true"


def run_args(synth_dir, cache_dir, store, *extra) -> list[str]:
    """``fedlgr run``'s arguments for the fast config on ``synth_dir``, one CPU thread,
    every metric logged, ``extra`` before the store."""
    return [
        str(FAST),
        f"data.path={synth_dir}",
        f"data.cache_dir={cache_dir}",
        "runtime.threads=1",
        "runtime.accelerator=cpu",
        DETAIL,
        *extra,
        f"--tracking-uri={store}",
    ]


AS_MAIN = """
import runpy, sys
sys.argv = ["fedlgr", *sys.argv[1:]]
runpy.run_module("fedlgr", run_name="__main__", alter_sys=True)
"""


def child_env(**changes) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop(TELEMETRY, None)  # what a user's shell has: the CLI's default applies
    env.pop("PYTEST_CURRENT_TEST", None)  # MLflow checks more under pytest: not a user's run
    env.update(changes)
    return env


class Child:
    """``python -m fedlgr run ARGS`` in its own session; stdout read line by line as it
    comes (the run prints each round once it is logged and checkpointed), stderr kept in
    a file. As a context manager, a child still alive at the end is killed. ``prelude``:
    Python run first in the child (``-c``), before ``fedlgr`` runs as ``-m`` would."""

    def __init__(self, args: list[str], cwd: Path, name: str = "child", prelude: str = ""):
        self.stderr_path = cwd / f"{name}.stderr"
        self._stderr = self.stderr_path.open("w")
        start = ["-c", prelude + AS_MAIN] if prelude else ["-m", "fedlgr"]
        self.process = subprocess.Popen(
            [sys.executable, *start, "run", *args],
            cwd=cwd,
            env=child_env(),
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            text=True,
            start_new_session=True,
        )
        self.pid = self.process.pid
        self.out: list[str] = []
        self._lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self._lines.put(line)
        self._lines.put(None)

    def wait_for(self, pattern: str, limit: float = 240) -> str:
        """The first stdout line matching ``pattern`` (without reaping the process)."""
        deadline = time.monotonic() + limit
        while True:
            left = deadline - time.monotonic()
            assert left > 0, f"no line {pattern!r} in {limit} s: {self.out}"
            try:
                line = self._lines.get(timeout=left)
            except queue.Empty:
                continue
            assert line is not None, f"the run ended before {pattern!r}: {self.stderr()[-3000:]}"
            self.out.append(line)
            if re.match(pattern, line):
                return line

    def signal_and_wait(self, sig: int) -> tuple[int, float]:
        """Send ``sig``; the exit code and the seconds from the signal to the exit."""
        os.kill(self.pid, sig)
        sent = time.monotonic()
        code = self.process.wait(timeout=60)
        return code, time.monotonic() - sent

    def stderr(self) -> str:
        self._stderr.flush()
        return self.stderr_path.read_text()

    def __enter__(self) -> Child:
        return self

    def __exit__(self, *exc) -> None:
        if self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.pid, signal.SIGKILL)
            self.process.wait()
        self._stderr.close()


# A full-width model on 4 clients: a run's checkpoint is ~120 MB, which torch.save writes
# for a few tenths of a second (0.25-1.7 s seen on 2 busy cores).
BIG_CHECKPOINT = ("model.width=1.0", "data.clients=4")


def partial_checkpoint(
    folder: Path, process: subprocess.Popen, pattern: str = ".round-*.ckpt.tmp", limit: float = 240
) -> Path:
    """A checkpoint being written under ``folder`` (a temporary ``pattern`` file, polled
    every millisecond) once its first megabyte is on disk: torch.save is then writing the
    tensors, past the pickling of the state that comes first."""
    deadline = time.monotonic() + limit
    while True:
        assert process.poll() is None, f"the process ended ({process.returncode}) before {pattern}"
        assert time.monotonic() < deadline, f"no {pattern} under {folder} in {limit} s"
        for path in folder.glob(f"*/{pattern}"):
            try:
                if path.stat().st_size >= 1 << 20:
                    return path
            except FileNotFoundError:  # renamed into place meanwhile
                continue
        time.sleep(0.001)


def experiment_runs(store: str, experiment: str = EXPERIMENT) -> tuple[mlflow.MlflowClient, list]:
    client = mlflow.MlflowClient(store)
    found = client.get_experiment_by_name(experiment)
    return client, (client.search_runs([found.experiment_id]) if found else [])


def only_run(store: str, experiment: str = EXPERIMENT):
    client, runs = experiment_runs(store, experiment)
    assert len(runs) == 1, [(r.info.run_id, r.info.status) for r in runs]
    return client, runs[0]


def metric_steps(client, run_id: str, key: str = SENTINEL) -> list[int]:
    return sorted(m.step for m in client.get_metric_history(run_id, key))
