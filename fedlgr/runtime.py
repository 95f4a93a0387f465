"""Process-level tuning that the command line and the benchmarks apply at start-up."""

from __future__ import annotations

import contextlib
import ctypes
import os
import platform
import threading
from collections.abc import Iterator

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8
_MMAP_THRESHOLD = 32 * 1024 * 1024  # glibc's largest allowed value on 64-bit
_TRIM_THRESHOLD = 512 * 1024 * 1024


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


_global_rng = threading.Lock()


@contextlib.contextmanager
def seeded_global_rng(seed: int) -> Iterator[None]:
    """torch's global CPU RNG seeded with ``seed`` inside the block and restored after it,
    one thread at a time: for code that draws from it and takes no generator (a module's
    ``reset_parameters``). Clients trained side by side (``runtime.concurrency=threads``)
    would otherwise reseed it under each other's feet."""
    import torch

    with _global_rng, torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


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
