"""Process-level tuning that the command line and the benchmarks apply at start-up."""

from __future__ import annotations

import ctypes
import os
import platform
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fedlgr.shell.config import ExperimentConfig

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8
_MMAP_THRESHOLD = 32 * 1024 * 1024  # glibc's largest allowed value on 64-bit
_TRIM_THRESHOLD = 512 * 1024 * 1024


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def default_threads(processes: int = 1) -> int:
    """torch threads for each of ``processes`` processes when ``runtime.threads`` is unset:
    the cores other work leaves idle (:func:`busy_cores`), shared out, at least 1.

    torch's OpenMP teams wait for their slowest thread at every operator, spinning while
    they wait: on a busy machine a team wider than the idle cores loses a thread to another
    process at each step and burns CPU in the meantime. The issue that set this default saw
    a debug round take 43.7 CPU s per client with every core vs 0.1 s with one thread; here
    (2 cores, load average 3.8, ``conf/debug/fast.yaml`` for 3 rounds, clients one after
    another) 2 threads took 1.0-6.7 s a round and 0.3-2.9 CPU s per client, 1 thread
    0.2-0.3 s and under 0.05 CPU s. On an idle machine this is all cores, as before."""
    cores = available_cores()
    idle = min(cores, max(1, int(cores - busy_cores() + 0.5)))  # rounded half up
    return max(1, idle // processes)


def busy_cores(sample_s: float = 0.25) -> float:
    """How many of this process's cores other work keeps busy: the lesser of the 1-minute
    load average (scaled to these cores: a cpuset sees the whole machine's load) and the
    cores' use over a ``sample_s`` sample (while this process sleeps). Either alone misleads:
    the load average still holds the last minute of this process's own previous run (a
    demo's second run, a sweep's next trial) and a start-up's imports, and one sample
    can catch a passing burst. Busy by both counts is busy."""
    import psutil  # lazy: psutil (~0.1 s), kept off `fedlgr --help`

    cores = available_cores()
    try:
        load = os.getloadavg()[0] * cores / (os.cpu_count() or cores)
    except (AttributeError, OSError):  # no load average (Windows): the sample decides
        load = float(cores)
    percent = psutil.cpu_percent(interval=sample_s, percpu=True)
    mine = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    used = [percent[i] for i in mine if i < len(percent)] if mine else percent
    return min(load, sum(used) / 100)


def tune_allocator() -> bool:
    """Have glibc keep freed blocks of up to 32 MB for reuse instead of unmapping them.

    Every training and augmentation step allocates and frees tensors of a few MB. glibc
    serves those with fresh ``mmap``s and hands them back on ``free``, so each step faults
    its pages in again; on the 2-core VMs this project runs on that made the augmented
    pipeline swing between 450 and 6600 images/s from run to run (``bench/data.py``), and
    steady at 4300-5500 with this setting. PyTorch's CPU performance guide recommends
    jemalloc or tcmalloc for the same reason; ``mallopt`` needs no extra dependency.

    And one arena for every thread: glibc gives each new thread's allocations an arena of
    64 MB heaps, which a step's 8-25 MB activations overflow and release again, faulting
    the pages in anew - clients trained side by side in threads (``runtime.concurrency``)
    fell from 118 to 75 images/s over three rounds with per-thread arenas and held 104-113
    with one (``bench/train.py``, 2 cores). Tensors are few and large, so the one lock
    costs little.
    Returns whether the settings were applied; ``FEDLGR_DEFAULT_MALLOC=1`` opts out.
    """
    if os.environ.get("FEDLGR_DEFAULT_MALLOC") == "1" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    return all(
        libc.mallopt(option, value)
        for option, value in (
            (_M_MMAP_THRESHOLD, _MMAP_THRESHOLD),
            (_M_TRIM_THRESHOLD, _TRIM_THRESHOLD),
            (_M_ARENA_MAX, 1),
        )
    )


def torch_threads(config: ExperimentConfig, local_world_size: int) -> int:
    """Threads per process: the setting, else this machine's idle cores over its processes
    (:func:`default_threads`: all cores would oversubscribe a busy one)."""
    if config.runtime.threads is not None:
        return config.runtime.threads
    return default_threads(local_world_size)
