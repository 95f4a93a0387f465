"""What a component keeps between rounds, and the process-wide random generators: moving
nested state to a device, capturing and restoring the generators (part of every runtime's
``state_dict``, so that a resumed run draws what the uninterrupted one drew), and seeding
torch's global generator for code that takes no generator of its own."""

from __future__ import annotations

import contextlib
import os
import random
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch


def to_device(value, device: torch.device | str):
    """``value`` with every tensor moved to ``device`` (dicts, lists, tuples walked)."""
    if isinstance(value, torch.Tensor):
        # Generator states are CPU byte tensors whatever the device; keep them there.
        return value if value.dtype == torch.uint8 else value.to(device)
    if isinstance(value, dict):
        return {k: to_device(v, device) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(to_device(v, device) for v in value)
    return value


def rng_states() -> dict[str, Any]:
    """The process-wide generators (Python, numpy, torch CPU and CUDA)."""
    return {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }


def set_rng_states(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_states` returned."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


_global_rng = threading.Lock()


@contextlib.contextmanager
def seeded_global_rng(seed: int) -> Iterator[None]:
    """torch's global CPU RNG seeded with ``seed`` inside the block and restored after it,
    one thread at a time: for code that draws from it and takes no generator (a module's
    ``reset_parameters``). Clients trained side by side (``runtime.concurrency=threads``)
    would otherwise reseed it under each other's feet."""
    with _global_rng, torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


PRIVATE = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW  # a planted link is refused


def save_private(state: Any, path: Path, durable: bool = False) -> None:
    """``torch.save`` to ``path``, this user's only from the first byte whatever the umask (a
    client's private state, every client's model); ``durable``: on disk before it returns."""
    with open(os.open(path, PRIVATE, 0o600), "wb") as handle:
        os.fchmod(handle.fileno(), 0o600)  # a file an older fedlgr left keeps its mode otherwise
        torch.save(state, handle)
        if durable:
            handle.flush()
            os.fsync(handle.fileno())
