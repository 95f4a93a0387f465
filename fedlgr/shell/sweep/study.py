"""Run a sweep as an Optuna study: resumable, parallel (``--workers``, or other machines on one
database storage), pruned, tracked in MLflow as a parent run with a child run per trial."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from fedlgr.shell.signals import Terminated
from fedlgr.shell.sweep.checks import check_data_folders
from fedlgr.shell.sweep.space import SweepSpec
from fedlgr.shell.sweep.storage import DEFAULT_STORAGE
from fedlgr.shell.sweep.trials import all_failed, counts, nothing_left, ran, summary
from fedlgr.shell.sweep.worker import Worker
from fedlgr.shell.tracking.store import runs_hint
from fedlgr.shell.tracking.uri import mask_password


@dataclass
class SweepResult:
    study: Any
    parent_run_id: str
    done: bool
    # every trial failed (how many, the first error), or trials in a row did (the last one's)
    failure: str | None = None


def run_sweep(
    spec: SweepSpec,
    *,
    storage: str = DEFAULT_STORAGE,
    study_name: str | None = None,
    workers: int = 1,
    tracking_uri: str | None = None,
    cli_overrides: list[str] | None = None,
    worker_id: int = 0,
    echo: Callable[..., None] = print,
    settings_changed: bool = False,
) -> SweepResult:
    """Run (or resume) the sweep with ``workers`` processes: this one and ``workers - 1``
    ``fedlgr sweep`` subprocesses on the same storage. Refuses to start (ConfigError)
    when a trial's ``data.path`` is not a folder."""
    check_data_folders(spec)
    if workers > 1:  # the helpers' lines are echoed from threads: one line at a time
        echo = serialised(echo)
    worker = Worker(
        spec,
        storage,
        study_name=study_name,
        tracking_uri=tracking_uri,
        worker=worker_id,
        echo=prefixed(echo, "[w0] ") if workers > 1 else echo,
        settings_changed=settings_changed,
    )
    _announce(worker, worker_id, echo)
    if not worker.left_to_run():  # a relaunched study: the first process ends its parent run
        if worker_id > 0:
            return SweepResult(worker.study, worker.parent_run_id, True)
        echo(nothing_left(worker.study, spec, worker.parent.finish()))
        return SweepResult(worker.study, worker.parent_run_id, True, all_failed(worker.study))
    helpers = [_start_helper(worker, k, cli_overrides, echo) for k in range(1, workers)]
    done = _run_with_helpers(worker, helpers)
    if worker_id > 0:  # a --workers helper: the process that started it ends the parent run
        return SweepResult(worker.study, worker.parent_run_id, done)
    best = worker.parent.finish() if done or worker.stopped else None
    if worker.stopped:  # its best so far and trials.json are logged; it did not finish
        worker.parent.end("FAILED")
    echo("\n" + summary(worker.study, spec, best))
    echo(runs_hint(worker.parent.tracking_uri, worker.parent.experiment_id))
    failure = worker.stopped or (all_failed(worker.study) if done else None)
    return SweepResult(worker.study, worker.parent_run_id, done, failure)


def _announce(worker: Worker, worker_id: int, echo: Callable[..., None]) -> None:
    """The sweep's first lines: what it runs, where its study and runs are, how far it is."""
    spec = worker.spec
    _, running, waiting = counts(worker.study, spec)
    total, size = spec.n_trials, spec.space_size()
    echo(
        f"sweep {spec.name}: {spec.sampler}, {total} trials, {spec.direction} {spec.metric}; "
        f"study {worker.study.study_name!r} in {mask_password(worker.storage)} "
        # done: the finished trials, not a grid's total less its open points (the running too)
        f"({ran(worker.study)} done, {running} running, {waiting} queued); "
        f"MLflow experiment {worker.experiment!r}, "
        f"parent run {worker.parent_run_id}"
    )
    if worker.parent.moved and worker_id == 0:
        echo(worker.parent.moved)
    if spec.sampler == "tpe" and size is not None and size < total:
        echo(f"sweep {spec.name}: its space has {size} distinct points: it stops once each has run")


def _start_helper(
    worker: Worker, k: int, cli_overrides: list[str] | None, echo: Callable[..., None]
) -> tuple[subprocess.Popen, threading.Thread]:
    """Worker ``k``: ``fedlgr sweep`` on the same study, store and experiment, and the thread that
    relays its output, each line prefixed with its worker."""
    command = [sys.executable, "-m", "fedlgr", "sweep", str(worker.spec.path)]
    command += [*(cli_overrides or []), "--storage", worker.storage]
    command += ["--study", worker.study.study_name]
    command += ["--tracking-uri", worker.parent.tracking_uri, "--worker-id", str(k)]
    process = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        errors="replace",
        env={**os.environ, "PYTHONUNBUFFERED": "1"},  # lines as they come, not in blocks
    )
    return process, relay(process, f"[w{k}] ", echo)


def _run_with_helpers(
    worker: Worker, helpers: list[tuple[subprocess.Popen, threading.Thread]]
) -> bool:
    """Run this process's worker; then wait for the helpers, and their last lines."""
    try:
        return worker.run()
    except Terminated:
        # SIGTERM may have reached this process alone (docker stop, timeout): pass it on
        for process, _ in helpers:
            process.terminate()
        raise
    finally:
        for process, _ in helpers:
            try:
                process.wait()
            except KeyboardInterrupt:
                process.terminate()
        for _, thread in helpers:
            thread.join(timeout=5)  # its last lines, before the table


def serialised(echo: Callable[..., None]) -> Callable[..., None]:
    """``echo`` that one thread at a time may call, so lines never mix mid-line."""
    lock = threading.Lock()

    def say(*args: object, **kwargs: Any) -> None:
        with lock:
            echo(*args, **kwargs)

    return say


def prefixed(echo: Callable[..., None], prefix: str) -> Callable[..., None]:
    """``echo`` with ``prefix`` before each non-empty line: two workers' lines interleave,
    and the prefix tells them apart."""

    def say(*args: object, **kwargs: Any) -> None:
        text = " ".join(map(str, args))
        echo("\n".join(prefix + line if line else line for line in text.split("\n")), **kwargs)

    return say


def relay(process: subprocess.Popen, prefix: str, echo: Callable[..., None]) -> threading.Thread:
    """A thread that echoes a helper worker's output line by line, each with ``prefix``."""

    def pump() -> None:
        for line in process.stdout:
            echo(prefix + line.rstrip("\n") if line.strip() else "")
        process.stdout.close()

    thread = threading.Thread(target=pump, name=f"relay {prefix.strip()}", daemon=True)
    thread.start()
    return thread
