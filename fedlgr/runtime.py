"""Process-level tuning that the command line and the benchmarks apply at start-up."""

from __future__ import annotations

import ctypes
import os
import platform

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD = 32 * 1024 * 1024  # glibc's largest allowed value on 64-bit
_TRIM_THRESHOLD = 512 * 1024 * 1024


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def tune_allocator() -> bool:
    """Have glibc keep freed blocks of up to 32 MB for reuse instead of unmapping them.

    Every training and augmentation step allocates and frees tensors of a few MB. glibc
    serves those with fresh ``mmap``s and hands them back on ``free``, so each step faults
    its pages in again; on the 2-core VMs this project runs on that made the augmented
    pipeline swing between 450 and 6600 images/s from run to run (``bench/data.py``), and
    steady at 4300-5500 with this setting. PyTorch's CPU performance guide recommends
    jemalloc or tcmalloc for the same reason; ``mallopt`` needs no extra dependency.
    Returns whether the setting was applied; ``FEDLGR_DEFAULT_MALLOC=1`` opts out.
    """
    if os.environ.get("FEDLGR_DEFAULT_MALLOC") == "1" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)) and bool(
        libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD)
    )
