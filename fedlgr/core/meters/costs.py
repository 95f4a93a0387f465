"""What a client's training costs: CPU and wall seconds, GPU seconds, utilisation
and memory.

CPU seconds are the process's user + system time (all its threads, plus any child
processes) across the client's training when a process's clients run one after another,
so the difference belongs to that client. Clients trained side by side
(``runtime.concurrency=threads``) are measured per thread (``time.thread_time``), and the
process's CPU seconds over the concurrent section are then shared out in proportion
(:func:`share_process_cpu`). GPU utilisation is NVML's
device-wide figure sampled every 50 ms while the client trains (NVML reports no
per-process utilisation); peak memory is torch's allocator peak on the client's device.
GPU seconds are the client's own: the time between two CUDA events recorded on the stream
the client's work is queued on (its own stream with ``runtime.concurrency=threads``), at
the start and the end of its work (:class:`StreamTimer`): the span of its GPU work on that
stream, gaps where the stream waited for the host included. Clients stacked into one model
(``batched``) share one span, given out in proportion to their samples. Without an NVIDIA
GPU the GPU figures are absent (``None``), not errors.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import psutil
import torch

from fedlgr.core.metrics import Figures

SAMPLE_SECONDS = 0.05


@dataclass
class Usage:
    """What a block of work cost, as :func:`measure` fills it in."""

    cpu_s: float = 0.0
    wall_s: float = 0.0
    gpu_util: float | None = None  # mean %, while training (device-wide, NVML)
    gpu_mem_mb: float | None = None  # peak allocated
    gpu_s: float | None = None  # the span of the client's work on its CUDA stream

    def figures(self) -> Figures:
        """The costs by their keys (:data:`fedlgr.core.metrics.COSTS`); the GPU ones only
        where measured."""
        out = {"cost/cpu_s": self.cpu_s, "cost/wall_s": self.wall_s}
        for name in ("gpu_util", "gpu_mem_mb", "gpu_s"):
            if (value := getattr(self, name)) is not None:
                out[f"cost/{name}"] = float(value)
        return out


class StreamTimer:
    """GPU seconds of the work queued on the current CUDA stream of ``device`` between
    :meth:`start` and :meth:`stop`: two CUDA events with timing, recorded on that stream;
    :meth:`stop` waits for the second one (not for other streams' work)."""

    def __init__(self, device: torch.device):
        self.device = device
        self._start: torch.cuda.Event | None = None

    def start(self) -> None:
        self._start = torch.cuda.Event(enable_timing=True)
        self._start.record(torch.cuda.current_stream(self.device))

    def stop(self) -> float:
        end = torch.cuda.Event(enable_timing=True)
        end.record(torch.cuda.current_stream(self.device))
        end.synchronize()
        return self._start.elapsed_time(end) / 1000.0  # milliseconds


def _cpu_seconds(process: psutil.Process) -> float:
    times = process.cpu_times()
    total = times.user + times.system
    for child in process.children(recursive=True):
        try:
            t = child.cpu_times()
            total += t.user + t.system
        except psutil.Error:  # a child that ended meanwhile
            pass
    return total


class _NvmlSampler:
    """Samples NVML utilisation of one GPU in a background thread.

    ``torch.cuda.utilization`` asks NVML and maps CUDA_VISIBLE_DEVICES to NVML's indices.
    """

    def __init__(self, device: torch.device):
        self.device = device
        self.samples: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append(torch.cuda.utilization(self.device))
            self._stop.wait(SAMPLE_SECONDS)

    def __enter__(self) -> _NvmlSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def mean(self) -> float | None:
        return sum(self.samples) / len(self.samples) if self.samples else None


_nvml_ready: bool | None = None


def nvml_available() -> bool:
    """Is there an NVIDIA driver to ask? (Initialises NVML once per process.)"""
    global _nvml_ready
    if _nvml_ready is None:
        try:
            import pynvml  # lazy: NVML's bindings, asked once, where a GPU is measured

            pynvml.nvmlInit()
            _nvml_ready = True
        except Exception:
            _nvml_ready = False
    return _nvml_ready


def share_process_cpu(usages: list[Usage], process_cpu_s: float) -> None:
    """Clients measured per thread ran side by side, over which the process spent
    ``process_cpu_s``: give each its share in proportion to its own thread's CPU time.

    With one intra-op thread per client (the split wherever clients >= cores) a client's
    thread does all of its work and the shares are its thread times (the pool's idle main
    thread adds next to nothing). With more, the client's OpenMP helper threads are not
    in ``time.thread_time``; their time is shared out in the same proportion, and the
    clients' figures still add up to what the process spent."""
    own = sum(u.cpu_s for u in usages)
    if own <= 0:
        return
    for u in usages:
        u.cpu_s = process_cpu_s * u.cpu_s / own


def process_cpu_seconds() -> float:
    """This process's user + system CPU seconds (and its children's) so far."""
    return _cpu_seconds(psutil.Process())


@contextmanager
def measure(device: torch.device, per_thread: bool = False, timer=None) -> Iterator[Usage]:
    """Measure the block's cost; the yielded ``Usage`` is filled in when it ends.
    ``per_thread``: CPU seconds of the calling thread only (see the module docstring).
    ``timer``: what measures the GPU seconds (``start()``, ``stop() -> seconds``); by
    default a :class:`StreamTimer` on a CUDA device, none elsewhere."""
    usage = Usage()
    process = psutil.Process()

    def cpu() -> float:
        return time.thread_time() if per_thread else _cpu_seconds(process)

    cuda = device.type == "cuda"
    if timer is None and cuda:
        timer = StreamTimer(device)
    sampler = None
    if cuda:
        # This stream's earlier work is not the block's (other clients' streams run on)
        torch.cuda.current_stream(device).synchronize()
        if nvml_available():
            torch.cuda.reset_peak_memory_stats(device)
            sampler = _NvmlSampler(device).__enter__()
    if timer is not None:
        timer.start()
    cpu0, wall0 = cpu(), time.perf_counter()
    try:
        yield usage
    finally:
        if timer is not None:
            usage.gpu_s = timer.stop()  # waits for the block's last GPU work on the stream
        if cuda:
            torch.cuda.current_stream(device).synchronize()
        usage.wall_s = time.perf_counter() - wall0
        usage.cpu_s = cpu() - cpu0
        if sampler is not None:
            sampler.__exit__()
            usage.gpu_util = sampler.mean
            usage.gpu_mem_mb = torch.cuda.max_memory_allocated(device) / 2**20
