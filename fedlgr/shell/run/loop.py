"""The round loop of every runtime: :func:`run_rounds` walks the run's schedule
(:mod:`fedlgr.core.schedule`) over a :class:`Rounds`, which runs each round - the
in-process :class:`~fedlgr.core.in_process.Orchestrator`, or the Flower server's
:class:`~fedlgr.shell.deploy.flower.server_app.FlowerRounds`, whose clients are robots - and
hands each round to a :class:`~fedlgr.shell.run.recorder.Recorder`, which records the run
(MLflow, checkpoints, the failure record). What a run logs does not depend on where its
clients live.
"""

from __future__ import annotations

import contextlib
import itertools
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Protocol

from fedlgr.core.messages import RoundPlan
from fedlgr.core.records import RoundLog
from fedlgr.core.schedule import schedule
from fedlgr.shell.config import ExperimentConfig
from fedlgr.shell.console import Progress, duration
from fedlgr.shell.run.recorder import Recorder
from fedlgr.shell.run.result import ExperimentResult

EpochProgress = Callable[[int, int], None]  # ``progress(client, epoch)`` after a local epoch


class Rounds(Protocol):
    """A runtime's rounds: what the round loop asks of it."""

    @property
    def local_clients(self) -> int:
        """How many clients train in this process (0: none do, they are robots); the
        round's progress bar counts their local epochs."""
        ...

    def run_round(self, plan: RoundPlan, progress: EpochProgress | None = None) -> RoundLog:
        """Train, aggregate and evaluate the round ``plan``; its log (the same in every
        process). ``progress(client, epoch)`` after each local epoch of this process's
        clients."""
        ...

    def save(
        self,
        folder: Path | None,
        rounds: list[RoundLog],
        run_id: str | None,
        elapsed: float,
        keep: int,
        digest: str = "",
    ) -> Path | None:
        """Checkpoint the run after the last of ``rounds`` into ``folder`` (rank 0's; None
        in other processes), keeping its newest ``keep``; every process calls it."""
        ...


def run_rounds(
    rounds: Rounds, config: ExperimentConfig, recorder: Recorder
) -> ExperimentResult | None:
    """Run the rounds of ``config``'s schedule that ``recorder``'s run has not done yet
    (a resumed run has done some) on ``rounds``. Each round goes to the recorder, is
    checkpointed when due, shows its line and is told to the caller's ``on_round``.
    Whatever raises - a round, Ctrl-C or SIGTERM, an ``on_round`` that asks the run to
    stop (a sweep's pruner) - ends the run: the recorder keeps what it had and ends it
    FAILED or KILLED, and the exception goes on. The result in rank 0, else None."""
    steps = schedule(config)
    tasks = list(config.continual.tasks)
    with recorder.recording(steps) as result:
        eta = Eta(len(steps) - len(result.rounds))
        for plan in steps.after(len(result.rounds)):
            label = f"round {plan.round}/{len(steps)}"
            label += f" (task {tasks[plan.task]})" if tasks else ""
            shown = recorder.rank0 and config.runtime.progress
            with _local_training(label, rounds.local_clients, config, shown) as progress:
                log = rounds.run_round(plan, progress)
            metrics = recorder.record(plan, log)
            if recorder.checkpoint_due(plan.round):
                recorder.checkpoint(rounds.save)
            missing = f"  missing: client {', '.join(map(str, log.missing))}" if log.missing else ""
            recorder.say(f"{label}: {_scores(log)}  ({log.seconds:.1f} s{eta.step()}){missing}")
            recorder.tell(plan.round, metrics)  # the caller's on_round: raising stops the run
    return recorder.summary()


@contextlib.contextmanager
def _local_training(
    label: str, clients: int, config: ExperimentConfig, shown: bool
) -> Iterator[EpochProgress]:
    """A round's progress bar: it counts each local epoch of each of this process's
    ``clients`` (plugins may run more or fewer epochs than planned: it never overflows)."""
    epochs = config.train.epochs
    plan = f"{_count(clients, 'client')} x {_count(epochs, 'epoch')}"
    shown = shown and clients > 0
    with Progress(f"{label}, local training ({plan})", "client-epochs", shown) as bar:
        total, done = clients * epochs, itertools.count(1)
        yield lambda client, epoch: bar(min(next(done), total), total)


class Eta:
    """``, ETA 4 min`` after each round but the last: the rounds still to run times the
    mean wall time of this process's rounds so far (logging and checkpoints included)."""

    def __init__(self, rounds: int):
        self.rounds, self.done, self.start = rounds, 0, time.perf_counter()

    def step(self) -> str:
        self.done += 1
        left = self.rounds - self.done
        if left <= 0:
            return ""
        mean = (time.perf_counter() - self.start) / self.done
        return f", ETA {duration(mean * left)}"


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _scores(log: RoundLog) -> str:
    """One round's line; a score that is not a number (a diverged run) shows as such."""
    figures = [
        (name, log.mean(column))
        for name, column in (
            ("loss", "test_loss"),
            ("RMSE", "test_rmse"),
            ("PCC", "test_pcc"),
        )
    ]
    shown = "  ".join(f"{n} {'-' if v is None else f'{v:.3f}'}" for n, v in figures)
    cpu = log.mean("cpu_s")
    return shown + f"  CPU {'-' if cpu is None else f'{cpu:.1f}'} s/client"
