"""The address-space limit (``ulimit -v``) a command runs under, checked before the first
``import torch``: too small a one makes torch fail obscurely (``std::bad_alloc``)."""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.util
import resource
import sys
from collections.abc import Iterator
from pathlib import Path

from fedlgr.errors import FedlgrError, exception_chain, first_line

# What the ways of running out say (lower case): the loader's, the C library's, torch's allocator's,
# C++'s and oneDNN's (which maps its kernels when a convolution first runs).
_RAN_OUT = (
    "failed to map segment",
    "cannot allocate memory",
    "can't allocate memory",
    "bad_alloc",
    "could not create a primitive",
)


def address_space_limit() -> int | None:
    """The soft RLIMIT_AS in bytes (what applies to this process); None without one."""
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    return None if soft == resource.RLIM_INFINITY else soft


def too_small(verb: str, why: str) -> str:
    """One line: the limit, what did not fit in it, and how to raise it."""
    limit = address_space_limit()
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    if hard == resource.RLIM_INFINITY:
        how = "ulimit -v unlimited"
    elif limit is not None and hard > limit:
        how = f"up to the hard limit: ulimit -v {hard // 1024}"
    else:  # only a new shell (or root) can raise the hard limit
        how = f"ulimit -v unlimited in a new shell: this one cannot go above {_gb(hard)}"
    shown = "unlimited" if limit is None else _gb(limit)
    return (
        f"the address-space limit (ulimit -v) of {shown} is too small for fedlgr {verb}: "
        f"{why}; raise it ({how})"
    )


def out_of_address_space(err: BaseException, verb: str) -> str | None:
    """The one line for ``err`` when it (or what led to it) ran out of memory under an address-space
    limit; None otherwise, and without a limit."""
    if address_space_limit() is None:
        return None
    for cause in exception_chain(err):
        message = str(cause).lower()
        if isinstance(cause, MemoryError) or (
            isinstance(cause, (ImportError, OSError, RuntimeError))
            and any(sign in message for sign in _RAN_OUT)
        ):
            return too_small(verb, first_line(cause, 200))
    return None


def torch_libraries() -> int:
    """Bytes of torch's shared objects and, for a CUDA build, of the ``nvidia`` wheels' libraries,
    found without importing torch: about what a run maps for it."""
    spec = importlib.util.find_spec("torch")
    if spec is None or not spec.submodule_search_locations:
        return 0
    lib = Path(next(iter(spec.submodule_search_locations))) / "lib"
    files = list(lib.glob("*.so*"))
    if (lib / "libtorch_cuda.so").exists():
        nvidia = importlib.util.find_spec("nvidia")
        folders = (nvidia.submodule_search_locations or []) if nvidia is not None else []
        for folder in folders:
            files += Path(folder).glob("*/lib/*.so*")
    return sum(f.stat().st_size for f in files if f.is_file())


def check_room_for_torch(verb: str) -> None:
    """Refuse a limit that cannot hold this process and torch's shared objects."""
    limit = address_space_limit()
    if limit is None:
        return
    import psutil  # lazy: psutil, kept off `fedlgr --help`

    used, libraries = psutil.Process().memory_info().vms, torch_libraries()
    if used + libraries > limit:
        raise FedlgrError(
            too_small(
                verb,
                f"this process ({_gb(used)}) and torch's shared objects with the CUDA "
                f"libraries installed beside it ({_gb(libraries)}) take more",
            )
        )


def _gb(n: int) -> str:
    """``4.07 GB``: two decimals, so that a limit and what did not fit in it compare."""
    return f"{n / 1e9:.2f} GB"


class _TorchGuard(importlib.abc.MetaPathFinder):
    """Checks the limit (:func:`check_room_for_torch`) when ``torch`` is first imported,
    then leaves the import to Python's own finders."""

    def __init__(self, verb: str):
        self.verb = verb

    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            with contextlib.suppress(ValueError):
                sys.meta_path.remove(self)  # once: torch's own imports pass freely
            check_room_for_torch(self.verb)
        return None


@contextlib.contextmanager
def torch_guarded(verb: str) -> Iterator[None]:
    """Within the block, the first ``import torch`` first checks that an address-space limit leaves
    room for it: too small a limit makes the import abort the process (``std::bad_alloc``). Nothing
    changes without a limit, or once torch is loaded."""
    if address_space_limit() is None or "torch" in sys.modules:
        yield
        return
    guard = _TorchGuard(verb)
    sys.meta_path.insert(0, guard)
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):
            sys.meta_path.remove(guard)
