"""Clients of one process trained side by side (``runtime.concurrency``).

A batch of 16 small images cannot keep many cores busy; several clients can. With
``threads`` a process's clients train in a pool of ``runtime.workers`` Python threads and
the process's torch threads are split between them: on 2 cores, 2 clients train at once
with one intra-op thread each instead of one after another with two (``bench/train.py``
measures both, and 2 processes as the reference). PyTorch releases the GIL inside its
operators, and OpenMP's thread count is a per-thread setting (``torch.set_num_threads``
in a worker sets that worker's own team size), so the split needs no extra processes.

Results are those of sequential training with the same threads per client: every client
has its own model, optimiser, plugins and generators, and nothing in training draws from
a process-wide RNG. (A different thread count per client changes the order of some
floating-point sums, so the effective ``runtime.threads``, ``concurrency`` and ``workers``
are recorded in the run's config, as for ``runtime.threads`` alone.)

On a GPU each worker issues its work on its own CUDA stream, which first waits for the
work queued before the pool; ``batched`` stacks the clients into one model instead
(:mod:`fedlgr.core.client.stacked`); docs/runtimes.md says which is the default
where, and what has been measured.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

import torch

if TYPE_CHECKING:
    from fedlgr.core.settings import ExperimentConfig


T = TypeVar("T")
R = TypeVar("R")


@dataclass(frozen=True)
class Resolved:
    """What a process decides at run time about how its clients train, once: its torch
    threads, its clients' concurrency and how many train at once. The results depend on
    them (the order of floating-point sums), so the run records them as its
    ``runtime.*`` settings (:meth:`recorded`) and a resumed run adopts them."""

    threads: int | None  # None: torch's own (a GPU process whose threads were not set)
    concurrency: str  # sequential | threads | batched
    workers: int

    @classmethod
    def decide(
        cls,
        concurrency: str,
        workers: int | None,
        threads: int | None,
        device: torch.device,
        clients: int,
    ) -> Resolved:
        """For a process with ``threads`` torch threads holding ``clients`` clients on
        ``device``: ``concurrency=auto`` is threads on CPU where a process has several
        clients and threads, else sequential; threads train ``workers`` clients at once
        (default: one per thread, at most one per client)."""
        count = threads or torch.get_num_threads()
        mode = concurrency
        if mode == "auto":
            several = clients > 1 and (device.type != "cpu" or count > 1)
            mode = "threads" if several and device.type == "cpu" else "sequential"
        at_once = 1
        if mode == "threads":
            default = count if device.type == "cpu" else clients
            at_once = max(1, min(workers or default, clients))
        return cls(threads, mode, at_once)

    def recorded(self, config: ExperimentConfig) -> ExperimentConfig:
        """``config`` as the run records it (params, checkpoints): with these choices."""
        runtime = dataclasses.replace(
            config.runtime,
            threads=self.threads,
            concurrency=self.concurrency,
            workers=self.workers,
        )
        return dataclasses.replace(config, runtime=runtime)


def _start_worker(threads: int, local: threading.local, device: torch.device) -> None:
    torch.set_num_threads(threads)  # this thread's OpenMP team size
    if device.type == "cuda":
        local.stream = torch.cuda.Stream(device)


class ClientPool:
    """Runs one function per client in ``workers`` threads, each with its share of the
    process's torch threads (and, on a GPU, its own CUDA stream)."""

    def __init__(self, workers: int, threads: int, device: torch.device):
        self.workers, self.device = workers, device
        self.threads_each = max(1, threads // workers)
        self._local = threading.local()
        # Set when the main thread is interrupted (Ctrl-C, SIGTERM): training loops that
        # are given it stop at their next step instead of finishing the client's round.
        self.stop = threading.Event()
        # The initializer must not hold the pool: the executor's threads exit when it is
        # garbage-collected, which a bound method of the pool would prevent (each dropped
        # pool left its workers behind: a sweep's trials piled them up).
        self._executor = (
            ThreadPoolExecutor(
                workers,
                "fedlgr-client",
                initializer=_start_worker,
                initargs=(self.threads_each, self._local, device),
            )
            if workers > 1
            else None
        )

    def _run(self, fn: Callable[[T], R], item: T) -> R:
        stream = getattr(self._local, "stream", None)
        if stream is None:
            return fn(item)
        # Wait for what the main thread queued (downloads) before using the tensors, and
        # finish before handing the results back.
        stream.wait_stream(torch.cuda.default_stream(self.device))
        with torch.cuda.stream(stream):
            out = fn(item)
        stream.synchronize()
        return out

    def each_worker(self, fn: Callable[[], object]) -> None:
        """``fn()`` once in every worker thread (with its thread count; e.g. a warm-up
        step, whose kernels are chosen per thread count); in this thread without a pool."""
        if self._executor is None:
            fn()
            return
        arrived = threading.Barrier(self.workers)  # holds each worker until all have one

        def once(_: int) -> None:
            arrived.wait(timeout=600)
            fn()

        self.map(once, range(self.workers))

    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
        """``[fn(item) for item in items]``, side by side; an error is raised once every
        item started has finished (the rest are not started)."""
        if self._executor is None:
            return [fn(item) for item in items]
        # A single item goes to a worker too: its thread count, hence its numbers, are
        # then those of every other item (and of sequential runs with that count).
        main_threads = torch.get_num_threads()
        futures = [self._executor.submit(self._run, fn, item) for item in items]
        try:
            return [f.result() for f in futures]
        except BaseException:
            self.stop.set()
            raise
        finally:
            for f in futures:
                f.cancel()
            for f in futures:
                if not f.cancelled():
                    f.exception()  # wait: no client trains on after the round ended
            self.stop.clear()
            # ``set_num_threads`` in a worker also sets the default of threads made later.
            torch.set_num_threads(main_threads)
