"""Process-level tuning that the command line and the benchmarks apply at start-up."""

from __future__ import annotations

import ctypes
import os
import platform
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fedlgr.shell.config import ExperimentConfig

_MALLOPT = {  # mallopt(3)'s option: value
    -3: 32 * 1024 * 1024,  # M_MMAP_THRESHOLD: glibc's largest allowed value on 64-bit
    -1: 512 * 1024 * 1024,  # M_TRIM_THRESHOLD
    -8: 1,  # M_ARENA_MAX
}


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def default_threads(processes: int = 1) -> int:
    """torch threads for each of ``processes`` processes when ``runtime.threads`` is unset: the
    cores other work leaves idle (:func:`busy_cores`), shared out, at least 1. torch's OpenMP teams
    spin while waiting for their slowest thread, so on a busy machine a wider team burns CPU."""
    cores = available_cores()
    idle = min(cores, max(1, int(cores - busy_cores() + 0.5)))  # rounded half up
    return max(1, idle // processes)


def busy_cores(sample_s: float = 0.25) -> float:
    """How many of this process's cores other work keeps busy: the lesser of the 1-minute load
    average (scaled to these cores) and their use over a ``sample_s`` sample. Either alone misleads:
    the load average still holds this process's previous run, a sample can catch a passing burst."""
    import psutil  # lazy: psutil, kept off `fedlgr --help`

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
    """Have glibc keep freed blocks of up to 32 MB for reuse and give every thread one arena, so
    that each step's tensors of a few MB do not fault their pages in anew. Returns whether the
    settings were applied; ``FEDLGR_DEFAULT_MALLOC=1`` opts out."""
    if os.environ.get("FEDLGR_DEFAULT_MALLOC") == "1" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    return all(libc.mallopt(option, value) for option, value in _MALLOPT.items())


def torch_threads(config: ExperimentConfig, local_world_size: int) -> int:
    """Threads per process: the setting, else this machine's idle cores over its processes
    (:func:`default_threads`: all cores would oversubscribe a busy one)."""
    threads = config.runtime.threads
    return default_threads(local_world_size) if threads is None else threads
