"""Run one experiment: set up Fabric, launch the processes, loop over rounds, track it.

``run_experiment(config)`` returns an :class:`ExperimentResult` in the process that
called it (rank 0). Multi-process runs use Fabric's launchers: ``runtime.launcher=ddp``
re-runs the current command once per extra process (what ``fedlgr run`` uses; several
nodes via ``fabric run`` / torchrun, which start the processes themselves), ``ddp_spawn``
spawns them from Python.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import itertools
import time
from dataclasses import dataclass
from pathlib import Path

from fedlgr.config import ExperimentConfig
from fedlgr.console import Progress, duration
from fedlgr.federated import concurrency
from fedlgr.federated.orchestrator import Orchestrator, torch_threads
from fedlgr.federated.result import ExperimentResult
from fedlgr.federated.rounds import RoundLog
from fedlgr.runtime import available_cores


def _epoch_counter(bar: Progress, total: int):
    """A ``progress(client, epoch)`` callback that advances ``bar`` by one epoch per call
    (plugins may run more or fewer epochs than planned: the bar never overflows)."""
    done = itertools.count(1)
    return lambda client, epoch: bar(min(next(done), total), total)


def make_fabric(config: ExperimentConfig):
    from lightning.fabric import Fabric
    from lightning.fabric.strategies import DDPStrategy

    rt = config.runtime
    accelerator = "cuda" if rt.accelerator == "gpu" else rt.accelerator
    if accelerator == "cuda":
        import torch

        from fedlgr.errors import FedlgrError

        if not torch.cuda.is_available():
            raise FedlgrError(
                f"runtime.accelerator={rt.accelerator}: no CUDA GPU on this machine "
                "(torch.cuda.is_available() is False); use runtime.accelerator=auto or cpu"
            )
    strategy = "auto"
    if rt.world_size > 1:
        # Models are never wrapped in DDP (clients train independently); buffers must
        # not be broadcast between processes either.
        timeout = datetime.timedelta(seconds=rt.timeout_s)
        strategy = (
            DDPStrategy(start_method="spawn", broadcast_buffers=False, timeout=timeout)
            if rt.launcher == "ddp_spawn"
            else DDPStrategy(broadcast_buffers=False, timeout=timeout)
        )
    return Fabric(
        accelerator=accelerator,
        devices=rt.devices,
        num_nodes=rt.num_nodes,
        strategy=strategy,
        precision=config.train.precision,
    )


def run_experiment(
    config: ExperimentConfig,
    *,
    parent_run_id: str | None = None,
    tags: dict[str, str] | None = None,
    echo=None,
    on_round=None,
    on_start=None,
    resume: str | bool | None = None,
    show_runs: bool = True,
) -> ExperimentResult | None:
    """Run ``config`` end to end; the result in rank 0, ``None`` in other processes.

    ``resume``: a run id, or True for the latest unfinished run of this config, to
    continue from its last checkpoint inside the same MLflow run. ``on_start(run_id)``
    (rank 0) is called once the MLflow run exists. ``on_round(round, metrics)`` (rank 0,
    after each round is logged and checkpointed; a resumed run first calls it again for
    the rounds it restored) may raise to stop the run, e.g. a sweep's
    pruner: the run is then ended KILLED if the exception has ``mlflow_status =
    "KILLED"``, FAILED otherwise, keeping what was logged. ``show_runs``: print at the
    end where to see the run in MLflow's UI."""
    from fedlgr.tracking.mlflow_run import tracking_uri
    from fedlgr.tracking.server import check_reachable

    if config.tracking.enabled:  # before any work: an unreachable server fails at once
        check_reachable(tracking_uri(config))
    from lightning.fabric.connector import _is_using_cli

    echo = echo or functools.partial(print, flush=True)  # progress must reach logs at once
    fabric = make_fabric(config)
    hooks = Hooks(echo, on_round, on_start, show_runs)
    if config.runtime.world_size == 1 or _is_using_cli():
        return _main(fabric, config, parent_run_id, tags, hooks, resume)
    return _launch(fabric, config, parent_run_id, tags, hooks, resume)


def _launch(fabric, config: ExperimentConfig, *args):
    """``fabric.launch(_main, ...)``. While the processes join (torch's rendezvous, which
    blocks in C++ where Python's signal handlers never run) SIGTERM and Ctrl-C keep their
    default action, ending the process at once: no MLflow run exists yet. A process that
    waits ``runtime.timeout_s`` for the others in vain is one line."""
    import signal

    from torch.distributed import DistBackendError, DistNetworkError, DistStoreError

    from fedlgr.errors import FedlgrError

    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    for number in handlers:
        signal.signal(number, signal.SIG_DFL)

    started: list[bool] = []

    def joined(fabric, *rest):
        started.append(True)
        for number, handler in handlers.items():
            signal.signal(number, handler)
        return _main(fabric, *rest)

    rt = config.runtime
    try:
        return fabric.launch(joined, config, *args)
    except (DistStoreError, DistNetworkError) as err:  # the latter: a process that joins
        if started:  # mid-run: a peer is gone
            raise FedlgrError(_peer_message(fabric, err)) from None
        import os

        where = f"{os.environ.get('MASTER_ADDR', '127.0.0.1')}:{os.environ.get('MASTER_PORT', '?')}"
        way_out = (
            "start the other nodes' processes (same command, their NODE_RANK) or check "
            "MASTER_ADDR/MASTER_PORT"
            if rt.num_nodes > 1
            else "this machine's processes start slowly when it is busy: raise runtime.timeout_s"
        )
        raise FedlgrError(
            f"runtime.num_nodes={rt.num_nodes}, runtime.devices={rt.devices}: not every process "
            f"joined within runtime.timeout_s={rt.timeout_s:g} s at {where} "
            f"({_one_line(err)}); {way_out}"
        ) from None
    except RuntimeError as err:  # after DistStoreError, one of its kind
        if not (isinstance(err, DistBackendError) or _peer_lost(err)):
            raise
        raise FedlgrError(_peer_message(fabric, err)) from None
    finally:
        for number, handler in handlers.items():
            if signal.getsignal(number) is signal.SIG_DFL:
                signal.signal(number, handler)


@dataclass
class Hooks:
    echo: object
    on_round: object = None
    on_start: object = None
    show_runs: bool = True


def _resume_point(
    fabric, config: ExperimentConfig, resume, adopt: frozenset[str] = frozenset()
) -> tuple[str, dict] | None:
    """Rank 0 finds the run and its checkpoint; every process then reads it (one machine,
    or a checkpoint folder every node can reach). A refusal is raised in every process."""
    from fedlgr.errors import FedlgrError
    from fedlgr.federated.resume import find_checkpoint, load_checkpoint
    from fedlgr.tracking.mlflow_run import open_client, tracking_uri

    if not resume:
        return None
    if not config.tracking.enabled:
        raise FedlgrError("--resume needs tracking.enabled=true (runs are found in MLflow)")
    found: tuple[str, str] | str = ""
    if fabric.global_rank == 0:
        try:
            run_id, path = find_checkpoint(config, resume, open_client(tracking_uri(config)))
            found = (run_id, str(path))
        except FedlgrError as err:
            found = str(err)
    if fabric.world_size > 1:
        found = fabric.broadcast(found, src=0)
    if isinstance(found, str):
        raise FedlgrError(found)
    run_id, path = found
    try:
        return run_id, load_checkpoint(config, run_id, Path(path), adopt)
    except BaseException:
        from fedlgr.tracking import owner

        owner.release(Path(path).parent)  # claimed by find_checkpoint (rank 0)
        raise


def _main(
    fabric, config: ExperimentConfig, parent_run_id, tags, hooks: Hooks, resume=None
) -> ExperimentResult | None:
    import torch
    from lightning.fabric import seed_everything

    from fedlgr.data.dataset import load_scenes
    from fedlgr.data.splits import make_split
    from fedlgr.federated.resume import MACHINE_CHOSEN, adopt_settings, restore, save_checkpoint

    chosen, share = config.runtime.threads, None
    # What this launch leaves to the machine: a resumed run takes its own values instead.
    left = {"runtime.threads": chosen, "runtime.workers": config.runtime.workers}
    left["runtime.concurrency"] = None if config.runtime.concurrency == "auto" else "set"
    machine = frozenset(k for k in MACHINE_CHOSEN if left[k] is None)
    if fabric.device.type == "cpu":
        # Results depend on the thread count (the order of floating-point sums): the
        # effective count goes into the config, its params and its checkpoints.
        local_world = fabric.world_size // config.runtime.num_nodes
        threads = torch_threads(config, local_world)
        share = None if chosen is not None else max(1, available_cores() // local_world)
        torch.set_num_threads(threads)
        config = dataclasses.replace(
            config, runtime=dataclasses.replace(config.runtime, threads=threads)
        )
    # How this process's clients train, made explicit (recorded like the thread count).
    local_clients = len(range(fabric.global_rank, config.data.clients, fabric.world_size))
    config = concurrency.resolve(config, fabric.device, local_clients)
    seed_everything(config.seed, verbose=False)
    start = time.perf_counter()
    point = _resume_point(fabric, config, resume, machine)
    if point is not None and machine:
        config = adopt_settings(config, point[1]["config"], machine)
        if fabric.device.type == "cpu" and config.runtime.threads:
            torch.set_num_threads(config.runtime.threads)
    show = fabric.global_rank == 0 and config.runtime.progress
    with Progress("decoding images", "img", show) as bar:  # only when not cached yet
        scenes = load_scenes(config.data, progress=bar)
    split = make_split(scenes.table, config.data)
    orchestrator = Orchestrator(fabric, config, scenes, split)
    resumed = None
    if point is not None:
        state = point[1]
        resumed = Resumed(
            point[0],
            restore(fabric, orchestrator, state),
            state["elapsed"],
            Path(state["path"]).parent,
            state.get("data_digest", ""),
        )
    processes = f", {fabric.world_size} processes" if fabric.world_size > 1 else ""
    return drive(
        orchestrator,
        config,
        hooks,
        rank0=fabric.global_rank == 0,
        tags=tags,
        parent_run_id=parent_run_id,
        what=f"{len(split.train)} training / {len(split.test)} test scenes{processes}, "
        + _threads_text(config, share),
        resumed=resumed,
        save=lambda folder, *rest: save_checkpoint(fabric, folder, orchestrator, *rest),
        start=start,
    )


def _threads_text(config: ExperimentConfig, share: int | None) -> str:
    """The header's account of the torch threads each process uses, and why when the
    default chose fewer than the process's ``share`` of the cores (others are busy)."""
    import torch

    rt = config.runtime
    threads = torch.get_num_threads()
    text = f"{threads} torch thread{'s' if threads != 1 else ''}"
    if share is not None and threads < share:
        text += f" (of {share} cores: the others are busy; runtime.threads to choose)"
    if rt.concurrency == "threads" and rt.workers > 1:
        text += f", {rt.workers} clients side by side"
    return text


@dataclass
class Resumed:
    run_id: str
    rounds: list[RoundLog]
    elapsed: float
    folder: Path | None = None  # the checkpoint folder it was resumed from (this process owns it)
    digest: str = ""  # of the data it trains on (checked against the checkpoint's)


def drive(
    rounds,
    config: ExperimentConfig,
    hooks: Hooks,
    *,
    rank0: bool = True,
    tags: dict[str, str] | None = None,
    parent_run_id: str | None = None,
    what: str = "",
    resumed: Resumed | None = None,
    save=None,
    start: float | None = None,
) -> ExperimentResult | None:
    """The schedule's round loop around ``rounds.run_round`` (an :class:`Orchestrator` or
    the Flower server's rounds): MLflow logging (rank 0), forgetting, checkpoints through
    ``save(folder, rounds, run_id, seconds, keep)``, the failure record and the summary.
    The same for every runtime: what a run logs does not depend on where clients live."""
    from fedlgr.continual.forgetting import ForgettingTracker
    from fedlgr.continual.schedule import schedule
    from fedlgr.tracking import owner
    from fedlgr.tracking.checkpoint import (
        checkpoint_root,
        checkpoints,
        remove,
        remove_temporaries,
    )
    from fedlgr.tracking.context import data_digest, run_name
    from fedlgr.tracking.mlflow_run import Tracker, tracking_uri

    start = time.perf_counter() if start is None else start
    say = hooks.echo if rank0 else (lambda *a, **k: None)
    tasks = list(config.continual.tasks)
    steps = schedule(config)
    forgetting = ForgettingTracker(tasks)
    result = ExperimentResult(config)
    elapsed = 0.0
    replayed: list[tuple[int, dict[str, float]]] = []  # restored rounds' metrics
    if resumed is not None:
        result.rounds = resumed.rounds
        for log, step in zip(result.rounds, steps, strict=False):
            metrics = {**log.metrics(), **forgetting.forgetting(log)}
            if step.last_of_task:  # the "after task" figures, as they were computed then
                metrics.update(forgetting.end_of_task(log, step.task))
            replayed.append((log.round, metrics))
        result.after_tasks = forgetting.after
        elapsed = resumed.elapsed
    tracker, folder = None, None
    old = resumed.folder if resumed is not None else None  # where its checkpoints were
    if rank0 and config.tracking.enabled:
        run_id = resumed.run_id if resumed is not None else None
        if config.tracking.checkpoint and save is not None:  # before the MLflow run exists
            try:
                owner.check_folder(checkpoint_root(config, tracking_uri(config)))
            except BaseException:
                owner.release(resumed.folder if resumed is not None else None)
                raise
        digest = (resumed.digest if resumed is not None else "") or data_digest(config)
        try:
            tracker = Tracker(config, tags, parent_run_id, run_id=run_id, digest=digest)
        except BaseException:
            owner.release(old)
            raise
        folder = checkpoint_root(config, tracking_uri(config)) / tracker.run_id
        result.run_id, result.data_digest = tracker.run_id, digest
    plan = (
        f"{len(tasks)} tasks ({', '.join(tasks)}) x {config.continual.rounds_per_task} rounds"
        if tasks
        else f"{config.federated.rounds} rounds"
    )
    say(
        f"{run_name(config)}: {plan} x {config.train.epochs} local epochs, "
        f"{config.data.clients} clients" + (f", {what}" if what else "")
    )
    if resumed is not None:
        say(f"resuming run {resumed.run_id} after round {len(result.rounds)} of {len(steps)}")
    every = config.tracking.checkpoint if config.tracking.enabled and save is not None else 0
    total = len(steps)
    local_clients = len(getattr(rounds, "clients", ()))
    missed: list[str] = []
    try:  # from here on the MLflow run exists: whatever happens, it is ended
        if tracker is not None:
            if every:
                owner.claim(folder, tracker.run_id)  # this process owns the run until it ends
                remove_temporaries(folder)  # of a write a kill cut short
                tracker.client.set_tag(tracker.run_id, "fedlgr.checkpoints", str(folder))
            if hooks.on_start is not None:
                hooks.on_start(tracker.run_id)
        if hooks.on_round is not None and rank0:
            # A run killed after a checkpoint but before ``on_round`` saw that round (e.g.
            # a sweep's report to Optuna) would lose it: the restored rounds are shown again
            # (a sweep ignores the repeats).
            for round_, metrics in replayed:
                hooks.on_round(round_, metrics)
        eta = Eta(total - len(result.rounds))
        for step in steps.after(len(result.rounds)):
            round_, k = step.round, step.task
            show = rank0 and config.runtime.progress and local_clients > 0
            label = f"round {round_}/{total}" + (f" (task {tasks[k]})" if tasks else "")
            # What the bar counts: each local epoch of each of this process's clients.
            plan = f"{_count(local_clients, 'client')} x {_count(config.train.epochs, 'epoch')}"
            with Progress(f"{label}, local training ({plan})", "client-epochs", show) as bar:
                epochs = local_clients * config.train.epochs
                log = rounds.run_round(
                    round_, k, step.first_of_task, step.last_of_task, _epoch_counter(bar, epochs)
                )
            result.rounds.append(log)
            metrics = {**log.metrics(), **forgetting.forgetting(log)}
            if step.last_of_task:
                metrics.update(forgetting.end_of_task(log, k))
                result.after_tasks = forgetting.after
            if tracker is not None:
                if log.initial:  # federated.server_eval: the initial model, at step 0
                    tracker.log_initial(log.initial)
                tracker.log_round(round_, metrics)
                if log.missing:  # robots that dropped out (fedlgr deploy)
                    missed.append(f"round {round_}: client {', '.join(map(str, log.missing))}")
                    tracker.client.set_tag(tracker.run_id, "fedlgr.missing", "; ".join(missed))
            if every and (round_ % every == 0 or round_ == total):
                spent = elapsed + time.perf_counter() - start
                keep = config.tracking.keep_checkpoints
                save(folder, result.rounds, result.run_id, spent, keep, result.data_digest)
                if old is not None and old != folder and folder is not None:
                    remove(old)  # moved (tracking.checkpoint_dir changed): the old one is stale
                    say(f"checkpoints moved from {old} to {folder}")
                    old = None
            missing = f"  missing: client {', '.join(map(str, log.missing))}" if log.missing else ""
            say(f"{label}: {_scores(log)}  ({log.seconds:.1f} s{eta.step()}){missing}")
            if hooks.on_round is not None and rank0:
                hooks.on_round(round_, metrics)
        result.seconds = elapsed + time.perf_counter() - start
        if tracker is not None:
            from fedlgr.tracking.plots import curves_png

            tracker.save_results(result.rows(), curves_png(result.rows(), run_name(config)))
            tracker.log_summary(result.cost_means(), len(result.rounds))
            heading = f"{run_name(config)} after {total} rounds ({result.seconds:.0f} s)"
            tracker.describe(heading, result.summary())
            tracker.finish()
    except BaseException as err:
        if tracker is not None:
            _record_failure(tracker, result, err, say)
        raise
    finally:
        if tracker is not None and getattr(tracker, "finished", False):
            if every:
                remove(folder)  # a finished run needs no checkpoint
            if old is not None:  # also when resumed with tracking.checkpoint=0
                remove(old)
        elif folder is not None and every and not checkpoints(folder) and folder != old:
            remove(folder)  # ended before its first checkpoint: only its lock file is there
        owner.release(folder)
        owner.release(old)
    if not rank0:
        return None
    say(f"\n{run_name(config)} after {total} rounds ({result.seconds:.0f} s):")
    say(result.summary())
    if tracker is not None and hooks.show_runs:
        from fedlgr.tracking.server import runs_hint

        if hint := runs_hint(tracker.uri, tracker.experiment_id):
            say(hint)
    return result


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


def _record_failure(tracker, result: ExperimentResult, err: BaseException, say) -> None:
    """Keep what the run had (results.csv, curves, costs) and end it KILLED or FAILED.
    Every step may fail on its own (a diverged run's NaNs, a store gone away): the run is
    still ended, and the original error is what the user sees."""
    from fedlgr.tracking.context import run_name
    from fedlgr.tracking.plots import curves_png

    name = run_name(tracker.config)
    steps = [
        ("results.csv", lambda: tracker.save_results(result.rows(), None)),
        ("curves.png", lambda: tracker.save_results([], curves_png(result.rows(), name))),
        ("cost summary", lambda: tracker.log_summary(result.cost_means(), len(result.rounds))),
    ]
    if result.rounds:
        for what, action in steps:
            try:
                action()
            except Exception as problem:  # reported; never raised over err
                say(f"(while failing: could not record {what}: {_one_line(problem)})")
    killed = isinstance(err, KeyboardInterrupt) or getattr(err, "mlflow_status", "") == "KILLED"
    try:
        tracker.fail(interrupted=killed)
    except Exception as problem:
        say(f"(while failing: could not end MLflow run {tracker.run_id}: {_one_line(problem)})")


def _peer_message(fabric, err: BaseException) -> str:
    return (
        f"another process of this {fabric.world_size}-process run ended during an exchange "
        f"({_one_line(err)}); its own output says why (killed, or an error); the run is "
        "ended FAILED and --resume continues it from its last checkpoint"
    )


def _peer_lost(err: BaseException) -> bool:
    """A collective failed because another process of the run is gone (gloo's words)."""
    text = str(err)
    return "gloo" in text and any(
        w in text for w in ("Connection reset by peer", "Connection closed by peer", "Read error")
    )


def _one_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0][:200] if text else type(err).__name__
