"""A run's life around a runtime's rounds (:class:`RunLife`): the MLflow run, checkpoints and
resume, the results and the failure record, the same for every runtime (in-process, Flower)."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fedlgr import __version__
from fedlgr.core.forgetting import ForgettingTracker
from fedlgr.core.metrics import SCORES, headline_scores
from fedlgr.core.privacy import epsilon
from fedlgr.core.records import RoundLog
from fedlgr.core.rounds import EpochProgress, Rounds
from fedlgr.core.schedule import Schedule, schedule
from fedlgr.errors import first_line
from fedlgr.shell.config import ExperimentConfig, flatten
from fedlgr.shell.console import Progress, duration
from fedlgr.shell.run import checkpoint as ckpt
from fedlgr.shell.run import owner
from fedlgr.shell.run.result import ExperimentResult
from fedlgr.shell.tracking.context import data_digest, run_name
from fedlgr.shell.tracking.mlflow_run import Tracker, tracking_uri
from fedlgr.shell.tracking.plots import curves_png
from fedlgr.shell.tracking.store import runs_hint

Metrics = dict[str, float]


@dataclass
class Hooks:
    """What the caller of a run hears of it (rank 0)."""

    echo: Callable[[str], object]  # a console line (``print``)
    # after each round is logged and checkpointed (restored ones again); raising stops the run
    on_round: Callable[[int, Metrics], object] | None = None
    on_start: Callable[[str], object] | None = None  # the MLflow run's id, once it exists
    show_runs: bool = True  # say at the end where to see the run in MLflow's UI


@dataclass
class Resumed:
    """A run picked up again from its last checkpoint (:mod:`fedlgr.shell.run.resume`)."""

    run_id: str
    state: dict[str, Any]  # the checkpoint
    folder: Path | None = None  # the checkpoint folder it was resumed from (this process owns it)


class RunLife:
    """One run's life: :meth:`run` a runtime's rounds. ``start``: its ``perf_counter`` start;
    ``what``, ``notes``: the header's account; ``fabric``: who checkpoints together."""

    def __init__(
        self,
        config: ExperimentConfig,
        hooks: Hooks,
        *,
        fabric=None,
        tags: dict[str, str] | None = None,
        parent_run_id: str | None = None,
        what: str = "",
        notes: Sequence[str] = (),
        resumed: Resumed | None = None,
        start: float | None = None,
    ):
        self.config, self.hooks, self.fabric = config, hooks, fabric
        self.rank0 = fabric is None or fabric.global_rank == 0
        self.tags, self.parent_run_id, self.what = tags, parent_run_id, what
        self.notes, self.resumed = list(notes), resumed
        self.start = time.perf_counter() if start is None else start
        self.elapsed = resumed.state["elapsed"] if resumed else 0.0  # before this launch
        self.result = ExperimentResult(config)
        self.forgetting = ForgettingTracker(list(config.continual.tasks))
        self.tracker: Tracker | None = None  # rank 0, tracking.enabled
        self.folder: Path | None = None  # the run's checkpoint folder (with the tracker)
        self.old = resumed.folder if resumed else None  # where its checkpoints were
        # every process checkpoints (rank 0 writes): every ``every`` rounds, 0: never
        self.every = config.tracking.checkpoint if config.tracking.enabled else 0
        self.total = 0  # rounds in the schedule
        self.missed: list[str] = []  # "round 2: client 1" (fedlgr.missing)
        self.refused: list[str] = []  # "round 2: client 1 (why)" (fedlgr.not_taken)
        self.outliers: list[str] = []  # "round 2: client 1: RMSE 0.010 (median 0.674)"

    def say(self, text: str) -> None:
        """A console line (rank 0)."""
        if self.rank0:
            self.hooks.echo(text)

    # ------------------------------------------------------------------ the rounds

    def run(self, rounds: Rounds) -> ExperimentResult | None:
        """Run on ``rounds`` the rounds of the schedule the run has not done yet: each is recorded,
        checkpointed when due, shown and told to ``on_round``; the result in rank 0."""
        steps = schedule(self.config)
        tasks = list(self.config.continual.tasks)
        if self.resumed is not None:
            rounds.load_state_dict(self.resumed.state)
        with self.recording(steps):
            first, began = len(self.result.rounds), time.perf_counter()
            for plan in steps.after(first):
                label = f"round {plan.round}/{len(steps)}"
                label += f" (task {tasks[plan.task]})" if tasks else ""
                shown = self.rank0 and self.config.runtime.progress
                with _local_training(label, rounds.local_clients, self.config, shown) as progress:
                    log = rounds.run_round(plan, progress)
                metrics = self.record(plan, log)
                saving, spent = time.perf_counter(), 0.0
                if self.every and (plan.round % self.every == 0 or plan.round == self.total):
                    self.checkpoint(rounds)  # every tracking.checkpoint rounds, and after the last
                    spent = time.perf_counter() - saving
                self.result.checkpoint_seconds.append(spent)
                eta = _eta(began, plan.round - first, len(steps) - plan.round)
                missing = (
                    f"  missing: client {', '.join(map(str, log.missing))}" if log.missing else ""
                )
                self.say(f"{label}: {_line(log)}  ({log.seconds:.1f} s{eta}){missing}")
                for client, why in sorted(log.refused.items()):
                    self.say(f"{label}: refused {log.who(client)}'s {why}")
                for client, what in sorted(log.capped.items()):
                    self.say(f"{label}: {log.who(client)}'s {what}")
                for client, what in log.outliers().items():
                    self.say(f"{label}: outlier {log.who(client)}: {what}")
                self.tell(plan.round, metrics)  # the caller's on_round: raising stops the run
        return self.summary()

    # ------------------------------------------------------------------ the run

    @contextlib.contextmanager
    def recording(self, steps: Schedule) -> Iterator[ExperimentResult]:
        """The run around the rounds of ``steps``: restores a resumed run, opens the MLflow run,
        says what it does; at its end the artifacts and FINISHED, else the failure record."""
        self.total = len(steps)
        try:  # once the MLflow run exists, whatever happens, it is ended
            if self.resumed is not None:  # its rounds, their metrics as computed then
                self.result.rounds = [round_log(r) for r in self.resumed.state["rows"]]
            done = zip(self.result.rounds, steps, strict=False)
            replayed = [(r.round, self._metrics(p, r)) for r, p in done]
            self._open()
            self._announce(steps)
            self._start(replayed)
            yield self.result
            self._finish()
        except BaseException as err:
            if self.tracker is not None:
                self._record_failure(self.tracker, err)
            raise
        finally:
            self._clean_up()

    def _open(self) -> None:
        """The MLflow run (rank 0, tracking.enabled); where its checkpoints go."""
        config, resumed = self.config, self.resumed
        if not (self.rank0 and config.tracking.enabled):
            return
        run_id = resumed.run_id if resumed is not None else None
        if config.tracking.checkpoint:  # before the MLflow run exists
            owner.check_folder(ckpt.checkpoint_root(config, tracking_uri(config)))
        saved = resumed.state.get("data_digest", "") if resumed is not None else ""  # "": older
        digest = saved or data_digest(config)
        self.tracker = tracker = Tracker(
            config, self.tags, self.parent_run_id, run_id=run_id, digest=digest
        )
        self.folder = ckpt.checkpoint_root(config, tracking_uri(config)) / str(tracker.run_id)
        self.result.run_id, self.result.data_digest = tracker.run_id, digest

    def _announce(self, steps: Schedule) -> None:
        config = self.config
        tasks = list(config.continual.tasks)
        plan = (
            f"{len(tasks)} tasks ({', '.join(tasks)}) x {config.continual.rounds_per_task} rounds"
            if tasks
            else f"{config.federated.rounds} rounds"
        )
        self.say(
            f"{run_name(config)}: {plan} x {config.train.epochs} local epochs, "
            f"{config.data.clients} clients" + (f", {self.what}" if self.what else "")
        )
        for note in self.notes:
            self.say(note)
        if config.federated.dp.enabled:
            self.say(_privacy(config, steps))
        if self.resumed is not None:
            done = len(self.result.rounds)
            self.say(f"resuming run {self.resumed.run_id} after round {done} of {self.total}")

    def _start(self, replayed: list[tuple[int, Metrics]]) -> None:
        """Own the checkpoint folder, tell ``on_start``; show the restored rounds again."""
        tracker = self.tracker
        if tracker is not None:
            if self.every and self.folder is not None:
                owner.claim(self.folder, str(tracker.run_id))  # this process owns the run
                ckpt.remove_temporaries(self.folder)  # of a write a kill cut short
                tracker.client.set_tag(tracker.run_id, "fedlgr.checkpoints", str(self.folder))
            if self.hooks.on_start is not None:
                self.hooks.on_start(str(tracker.run_id))
        # told again: a kill between a checkpoint and ``on_round`` would lose that round
        for round_, metrics in replayed:
            self.tell(round_, metrics)

    def _finish(self) -> None:
        """The run's time; its artifacts, summary and description; FINISHED."""
        result = self.result
        result.seconds = self.elapsed + time.perf_counter() - self.start
        tracker = self.tracker
        if tracker is None:
            return
        name = run_name(self.config)
        saving = time.perf_counter()
        tracker.save_results(result.rows(), curves_png(result.rows(), name))
        tracker.log_summary(result.cost_means(), len(result.rounds))
        heading = f"{name} after {self.total} rounds ({result.seconds:.0f} s)"
        tracker.describe(heading, result.summary(), result.final_metrics())
        result.results_seconds = time.perf_counter() - saving
        tracker.finish()

    def _clean_up(self) -> None:
        """A finished run needs no checkpoint; one that ended before its first checkpoint
        leaves no empty folder. Either way the folders are released."""
        tracker, folder, old = self.tracker, self.folder, self.old
        ours = not self.config.tracking.checkpoint_dir  # its root is fedlgr's checkpoints/
        if tracker is not None and getattr(tracker, "finished", False):
            if self.every and folder is not None:
                ckpt.remove(folder, ours)
            if old is not None:  # also when resumed with tracking.checkpoint=0
                ckpt.remove(old)
        elif folder is not None and self.every and not ckpt.checkpoints(folder) and folder != old:
            ckpt.remove(folder, ours)  # ended before its first checkpoint: only its lock file
        owner.release(folder)
        owner.release(old)

    # ------------------------------------------------------------------ each round

    def record(self, plan, log: RoundLog) -> Metrics:
        """The round ``plan`` has run: its log joins the result; its metrics (forgetting
        and after-task figures too) are logged to MLflow, and returned."""
        self.result.rounds.append(log)
        metrics = self._metrics(plan, log)
        tracker = self.tracker
        logging = time.perf_counter()
        if tracker is not None:
            if log.initial:  # federated.server_eval: the initial model, at step 0
                tracker.log_initial(log.initial)
            tracker.log_round(plan.round, metrics)
            if log.missing:  # robots that dropped out (fedlgr deploy)
                self.missed.append(f"round {plan.round}: client {', '.join(map(str, log.missing))}")
                tracker.client.set_tag(tracker.run_id, "fedlgr.missing", "; ".join(self.missed))
            if log.refused:  # uploads the server did not take
                self.refused += [
                    f"round {plan.round}: {log.who(c)} ({why})" for c, why in log.refused.items()
                ]
                refused = "; ".join(self.refused)
                tracker.client.set_tag(tracker.run_id, "fedlgr.not_taken", refused[-5000:])
            if outliers := log.outliers():  # scores far from the others' median
                self.outliers += [
                    f"round {plan.round}: {log.who(c)}: {w}" for c, w in outliers.items()
                ]
                said = "; ".join(self.outliers)
                tracker.client.set_tag(tracker.run_id, "fedlgr.outliers", said[-5000:])
        self.result.tracking_seconds.append(time.perf_counter() - logging)
        return metrics

    def _metrics(self, plan, log: RoundLog) -> Metrics:
        """A round's metrics and forgetting; at a task's end, the after-task figures too."""
        metrics = {**log.metrics(), **self.forgetting.forgetting(log)}
        if plan.last_of_task:
            metrics.update(self.forgetting.end_of_task(log, plan.task))
            self.result.after_tasks = self.forgetting.after
        return metrics

    def checkpoint(self, rounds: Rounds) -> Path | None:
        """Checkpoint the run after its last round (every process takes part, rank 0 writes),
        keeping the newest ``tracking.keep_checkpoints``; a resumed run's stale folder goes."""
        result = self.result
        state = rounds.state_dict()
        spent = self.elapsed + time.perf_counter() - self.start
        whole = checkpoint_state(self.config, result, state, spent) if self.rank0 else {}
        folder = self.folder if self.folder is not None else Path(".")  # rank 0's is used
        keep = self.config.tracking.keep_checkpoints
        path = ckpt.save(self.fabric, folder, result.rounds[-1].round, whole, keep)
        old = self.old
        if old is not None and old != self.folder and self.folder is not None:
            ckpt.remove(old)  # moved (tracking.checkpoint_dir changed): the old one is stale
            self.say(f"checkpoints moved from {old} to {self.folder}")
            self.old = None
        return path

    def tell(self, round_: int, metrics: Metrics) -> None:
        """The caller's ``on_round`` (rank 0), which may raise to stop the run."""
        if self.hooks.on_round is not None and self.rank0:
            self.hooks.on_round(round_, metrics)

    # ------------------------------------------------------------------ the end

    def summary(self) -> ExperimentResult | None:
        """Say the run's summary, and where to see it in MLflow's UI; the result in rank 0,
        None in other processes."""
        if not self.rank0:
            return None
        result = self.result
        self.say(f"\n{run_name(self.config)} after {self.total} rounds ({result.seconds:.0f} s):")
        self.say(result.summary())
        tracker = self.tracker
        hint = runs_hint(tracker.uri, tracker.experiment_id) if tracker is not None else ""
        if hint and self.hooks.show_runs:
            self.say(hint)
        return result

    def _record_failure(self, tracker: Tracker, err: BaseException) -> None:
        """Keep what the run had (results.csv, curves, its summary so far) and end it KILLED or
        FAILED, whatever step fails: the user sees the original error. No ``mean/*`` metrics: a
        resumed run logs those at its end, and MLflow cannot take a point back."""
        result = self.result
        name = run_name(tracker.config)
        killed = isinstance(err, KeyboardInterrupt) or getattr(err, "mlflow_status", "") == "KILLED"
        spent = self.elapsed + time.perf_counter() - self.start
        heading = (
            f"{name}: {'KILLED' if killed else 'FAILED'} after {len(result.rounds)} of "
            f"{self.total} rounds ({spent:.0f} s)"
        )
        steps = {
            "record results.csv": lambda: tracker.save_results(result.rows(), None),
            "record curves.png": lambda: tracker.save_results([], curves_png(result.rows(), name)),
            "record summary": lambda: tracker.describe(
                heading, result.summary(), result.final_metrics()
            ),
        }
        if not result.rounds:
            steps = {}
        steps[f"end MLflow run {tracker.run_id}"] = lambda: tracker.fail(interrupted=killed)
        for what, action in steps.items():
            try:
                action()
            except Exception as problem:  # reported; never raised over err
                self.say(f"(while failing: could not {what}: {first_line(problem, 200)})")


def checkpoint_state(
    config: ExperimentConfig, result: ExperimentResult, state: dict, elapsed: float
) -> dict[str, Any]:
    """A run's checkpoint after its last round: the runtime's ``state``, every round's rows, the
    resolved config, the MLflow run id, the time spent and the data's digest."""
    return {
        "format": ckpt.FORMAT,
        "fedlgr": __version__,
        "run_id": result.run_id,
        "round": result.rounds[-1].round,
        "config": flatten(config),
        **state,
        "rows": [round_state(r) for r in result.rounds],
        "elapsed": elapsed,
        "data_digest": result.data_digest,
    }


# a RoundLog in a checkpoint: lists for tuples, string keys by client; fields it lacks default
_BY_CLIENT = ("refused", "faults", "names", "capped")


def round_state(log: RoundLog) -> dict[str, Any]:
    state = {f.name: getattr(log, f.name) for f in dataclasses.fields(log)}
    for name in _BY_CLIENT:
        state[name] = {str(c): v for c, v in state[name].items()}
    for name in ("keys", "missing", "participants"):
        state[name] = None if state[name] is None else list(state[name])
    return state


def round_log(state: dict[str, Any]) -> RoundLog:
    known = {f.name for f in dataclasses.fields(RoundLog)}
    values = {k: v for k, v in state.items() if k in known}
    values["table"] = np.asarray(values["table"])
    values["missing"] = tuple(values["missing"])
    if values.get("participants") is not None:
        values["participants"] = tuple(values["participants"])
    for name in _BY_CLIENT:
        values[name] = {int(c): v for c, v in values.get(name, {}).items()}
    return RoundLog(**values)


@contextlib.contextmanager
def _local_training(
    label: str, clients: int, config: ExperimentConfig, shown: bool
) -> Iterator[EpochProgress]:
    """A round's progress bar over each local epoch of this process's ``clients``; capped, as
    plugins may run other epoch counts and a strategy may choose fewer clients."""
    epochs = config.train.epochs
    plan = f"{_count(clients, 'client')} x {_count(epochs, 'epoch')}"
    shown = shown and clients > 0
    with Progress(f"{label}, local training ({plan})", "client-epochs", shown) as bar:
        total, done = clients * epochs, itertools.count(1)
        yield lambda client, epoch: bar(min(next(done), total), total)


def _eta(began: float, done: int, left: int) -> str:
    """``, ETA 4 min`` after each round but the last: the rounds still to run times the
    mean wall time of this process's rounds so far (logging and checkpoints included)."""
    return f", ETA {duration((time.perf_counter() - began) / done * left)}" if left > 0 else ""


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _line(log: RoundLog) -> str:
    """One round's line: every score's headline over the clients (a diverged run's NaN shows as
    such; a round no client scored says so; a statistic that is not the mean is named) and,
    from three clients, the first's interquartile range; the simulated attackers' scores
    apart, and the CPU per client."""
    first = f"test/{headline_scores()[0].name}"
    # three clients or more: how far apart their scores lie
    spread = log.spread(first) if first in log.keys and log.counted.sum() >= 3 else None
    figures = [(s.label, log.mean(f"test/{s.name}")) for s in SCORES]
    shown = "  ".join(
        f"{n} {'-' if v is None else f'{v:.3f}'}"
        + (f" (IQR {spread:.3f})" if spread is not None and f"test/{s.name}" == first else "")
        for s, (n, v) in zip(SCORES, figures, strict=True)
    )
    if all(v is None for _, v in figures):  # federated.eval_every, or every scorer missing
        shown = "not scored"
    elif log.statistic != "mean":  # robots' scores: the robust strategy's statistic
        shown = f"{shown} ({log.statistic})"
    apart = [(s.label, log.apart(f"test/{s.name}")) for s in SCORES if s.headline]
    if any(v is not None for _, v in apart):  # simulated attackers: not in the headline
        shown += "  byzantine " + " ".join(f"{n} {v:.3f}" for n, v in apart if v is not None)
    cpu = log.mean("cost/cpu_s")
    shown += f"  CPU {'-' if cpu is None else f'{cpu:.1f}'} s/client"
    spent = log.server.get("privacy/epsilon")  # client-level DP: the budget spent so far
    return shown if spent is None else shown + f"  epsilon {spent:.2f}"


def _privacy(config: ExperimentConfig, steps: Schedule) -> str:
    """The run's client-level DP and, with a target epsilon, where it stops."""
    dp = config.federated.dp
    clip = f"{dp.clipping} clipping at {dp.clip:g}"
    line = f"client-level DP: {clip}, noise multiplier {dp.noise_multiplier:g}, delta {dp.delta:g}"
    if dp.noise_multiplier == 0:
        return f"client-level DP: {clip} and no noise - no privacy guarantee (epsilon infinite)"
    if dp.target_epsilon > 0:
        rate = config.federated.fraction
        spent = epsilon(dp.noise_multiplier, rate, len(steps), dp.delta)
        line += f"; target epsilon {dp.target_epsilon:g}: "
        if len(steps) < steps.planned:
            line += f"stops after round {len(steps)} of {steps.planned} (epsilon {spent:.2f})"
        else:
            line += f"all {len(steps)} rounds fit (epsilon {spent:.2f})"
    return line
