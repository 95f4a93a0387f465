"""Run one experiment in our processes: Fabric's set-up and launch, the resume point, the runtime
settings resolved once, the data, the in-process orchestrator and the run's life around them."""

from __future__ import annotations

import contextlib
import datetime
import functools
import os
import signal
import time

import torch
from lightning.fabric import Fabric, seed_everything
from lightning.fabric.connector import _is_using_cli
from lightning.fabric.strategies import DDPStrategy
from torch.distributed import DistBackendError, DistNetworkError, DistStoreError

from fedlgr.core.client.pool import Resolved
from fedlgr.core.data.scenes import FederatedSplit
from fedlgr.core.in_process import Orchestrator
from fedlgr.errors import FedlgrError, first_line
from fedlgr.shell.config import ExperimentConfig
from fedlgr.shell.console import Progress
from fedlgr.shell.data.dataset import load_split
from fedlgr.shell.data.splits import task_clients
from fedlgr.shell.machine import available_cores, torch_threads
from fedlgr.shell.run.checkpoint import checkpoint_root
from fedlgr.shell.run.life import Hooks, RunLife
from fedlgr.shell.run.result import ExperimentResult
from fedlgr.shell.run.resume import adopted, left_to_machine, resume_point
from fedlgr.shell.tracking.mlflow_run import tracking_uri


def make_fabric(config: ExperimentConfig):
    rt = config.runtime
    accelerator = "cuda" if rt.accelerator == "gpu" else rt.accelerator
    if accelerator == "cuda" and not torch.cuda.is_available():
        raise FedlgrError(
            f"runtime.accelerator={rt.accelerator}: no CUDA GPU on this machine "
            "(torch.cuda.is_available() is False); use runtime.accelerator=auto or cpu"
        )
    strategy = "auto"
    if rt.world_size > 1:
        # no DDP wrapping (clients train independently), and no buffers broadcast either
        timeout = datetime.timedelta(seconds=rt.timeout_s)
        start = "spawn" if rt.launcher == "ddp_spawn" else "popen"
        strategy = DDPStrategy(start_method=start, broadcast_buffers=False, timeout=timeout)
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
    """Run ``config`` end to end; the result in rank 0, ``None`` in other processes. ``resume``: a
    run id, or True for this config's latest unfinished run; ``on_round(round, metrics)`` may raise
    to stop the run. The caller has checked that the tracking store is reachable."""
    echo = echo or functools.partial(print, flush=True)  # progress must reach logs at once
    fabric = make_fabric(config)
    hooks = Hooks(echo, on_round, on_start, show_runs)
    if config.runtime.world_size == 1 or _is_using_cli():
        return _main(fabric, config, parent_run_id, tags, hooks, resume)
    return _launch(fabric, config, parent_run_id, tags, hooks, resume)


def _launch(fabric, config: ExperimentConfig, *args):
    """``fabric.launch(_main, ...)``, SIGTERM and Ctrl-C ending the process at once while the
    processes join: torch's rendezvous blocks in C++, where Python's signal handlers never run."""
    handlers = {s: signal.signal(s, signal.SIG_DFL) for s in (signal.SIGTERM, signal.SIGINT)}

    started: list[bool] = []

    def joined(fabric, *rest):
        started.append(True)
        for number, handler in handlers.items():
            signal.signal(number, handler)
        return _main(fabric, *rest)

    rt = config.runtime
    try:
        return fabric.launch(joined, config, *args)
    except RuntimeError as err:  # torch's DistError too
        # DistNetworkError: a process that joins; mid-run, either says that a peer is gone
        joining = isinstance(err, DistStoreError | DistNetworkError)
        if not (joining or isinstance(err, DistBackendError) or _peer_lost(err)):
            raise
        if started or not joining:
            raise FedlgrError(
                f"another process of this {fabric.world_size}-process run ended during an "
                f"exchange ({first_line(err, 200)}); its own output says why (killed, or an "
                "error); the run is ended FAILED and --resume continues it from its last checkpoint"
            ) from None
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
            f"({first_line(err, 200)}); {way_out}"
        ) from None
    finally:
        for number, handler in handlers.items():
            if signal.getsignal(number) is signal.SIG_DFL:
                signal.signal(number, handler)


def _main(
    fabric, config: ExperimentConfig, parent_run_id, tags, hooks: Hooks, resume=None
) -> ExperimentResult | None:
    """One process's run: the resume point, the runtime settings resolved once, the data, the
    in-process runtime and the run's life around it."""
    start = time.perf_counter()
    left = left_to_machine(config)
    resumed = resume_point(fabric, config, resume, left)
    resolved, share = _resolve(fabric, config, adopted(resumed, left))
    config = resolved.recorded(config)  # as its params and checkpoints keep it
    seed_everything(config.seed, verbose=False)
    show = fabric.global_rank == 0 and config.runtime.progress
    with Progress("decoding images", "img", show) as bar:  # only when not cached yet
        # split before decoding: a split the schedule cannot train is refused in a moment
        scenes, split = load_split(config.data, config.continual.tasks, progress=bar)
    # idle clients' states beyond runtime.idle_memory_mb: by the checkpoints
    spill = checkpoint_root(config, tracking_uri(config)) if config.tracking.enabled else None
    orchestrator = Orchestrator(fabric, config, scenes, split, spill, resolved)
    processes = f", {fabric.world_size} processes" if fabric.world_size > 1 else ""
    held = _task_clients(split)
    if held is not None:
        tags = {**(tags or {}), "fedlgr.task_clients": held[1]}
    life = RunLife(
        config,
        hooks,
        fabric=fabric,
        tags=tags,
        parent_run_id=parent_run_id,
        what=f"{len(split.train)} training / {len(split.test)} test scenes{processes}, "
        + _threads_text(config, share),
        notes=[held[0]] if held is not None else [],
        resumed=resumed,
        start=start,
    )
    try:
        return life.run(orchestrator)
    finally:
        orchestrator.close()
        if spill is not None and not config.tracking.checkpoint_dir:  # fedlgr's own folder
            with contextlib.suppress(OSError):  # not empty: checkpoints to resume, other runs
                spill.rmdir()  # made for the idle clients' files alone: not left behind empty


def _task_clients(split: FederatedSplit) -> tuple[str, str] | None:
    """Where some client holds no training scenes of a task (legal in plain FL): the header's line
    and the tag ``fedlgr.task_clients`` saying how many clients hold each; None where all do."""
    held, n = task_clients(split), len(split.clients)
    if min(held.values()) == n:
        return None
    return (
        "clients with training scenes of each task: "
        + ", ".join(f"{task} {k} of {n}" for task, k in held.items()),
        ", ".join(f"{task}:{k}/{n}" for task, k in held.items()),
    )


def _resolve(fabric, config: ExperimentConfig, adopted: dict) -> tuple[Resolved, int | None]:
    """How this process's clients train, decided once: as given, else as the resumed run did, else
    as the machine allows (torch threads: results depend on their count); and its core share."""
    rt = config.runtime
    threads, share = adopted.get("threads", rt.threads), None
    if fabric.device.type == "cpu":
        local_world = fabric.world_size // rt.num_nodes
        if threads is None:
            threads = torch_threads(config, local_world)
            share = max(1, available_cores() // local_world)
        torch.set_num_threads(threads)
    mine = len(range(fabric.global_rank, config.data.clients, fabric.world_size))
    concurrency = adopted.get("concurrency", rt.concurrency)
    workers = adopted.get("workers", rt.workers)
    return Resolved.decide(concurrency, workers, threads, fabric.device, mine), share


def _threads_text(config: ExperimentConfig, share: int | None) -> str:
    """The header's account of the torch threads each process uses, and why when the
    default chose fewer than the process's ``share`` of the cores (others are busy)."""
    rt = config.runtime
    threads = torch.get_num_threads()
    text = f"{threads} torch thread{'s' if threads != 1 else ''}"
    if share is not None and threads < share:
        text += f" (of {share} cores: the others are busy; runtime.threads to choose)"
    if rt.concurrency == "threads" and rt.workers > 1:
        text += f", {rt.workers} clients side by side"
    return text


def _peer_lost(err: BaseException) -> bool:
    """A collective failed because another process of the run is gone (gloo's words)."""
    text = str(err)
    return "gloo" in text and any(
        w in text for w in ("Connection reset by peer", "Connection closed by peer", "Read error")
    )
