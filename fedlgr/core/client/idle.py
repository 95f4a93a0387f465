"""What a client not at work in a round keeps (``runtime.idle_clients``): its state, not a
model.

A client's state (:meth:`Client.state_dict`: model, optimiser, plugins, batch generators)
is kept *compact*: the model's tensors that equal the global ones the client holds are
left out and taken from the global tensors when it is woken (the shared part of every
client is the same after its download; in FedRoot only the top is its own). What is left
is held in memory up to a budget of bytes and written to a file under ``folder`` beyond
it. A client is woken - given a model, an optimiser and plugins again - only to train,
to end a task or to be evaluated. A state goes through ``torch.save``/``torch.load``
unchanged, so a run's numbers are the same whether its idle clients are whole, compact in
memory or on disk (``tests/test_idle_clients.py``).
"""

from __future__ import annotations

import ctypes
import functools
import os
import shutil
import socket
from pathlib import Path

import torch

from fedlgr.core.messages import Weights
from fedlgr.core.state import save_private
from fedlgr.errors import FedlgrError

LIVE_UP_TO = 32  # runtime.idle_clients=auto: whole clients up to this many per process


def idle_keeping(runtime, clients: int) -> str:
    """How a process that holds ``clients`` clients keeps its idle ones: live, memory,
    disk, or auto (compact in memory up to ``runtime.idle_memory_mb``, the rest on disk)."""
    if runtime.idle_clients != "auto":
        return runtime.idle_clients
    return "live" if clients <= LIVE_UP_TO else "auto"


def spill_prefix() -> str:
    """The name a process's folder of idle states starts with: its machine and process."""
    return f".idle-clients-{socket.gethostname()}-{os.getpid()}-"


def remove_stale(parent: Path) -> None:
    """Remove the folders of idle states under ``parent`` left by killed processes of this
    machine (a process that ends otherwise removes its own)."""
    host = f".idle-clients-{socket.gethostname()}-"
    for folder in parent.glob(f"{host}*"):
        pid = folder.name.removeprefix(host).split("-", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(folder, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's
        return True
    return True


def give_back_freed_memory() -> None:
    """Hand the memory freed by resting clients back to the operating system (glibc's
    ``malloc_trim``; nothing elsewhere).

    Waking and resting clients a few at a time frees and allocates megabytes of tensors in
    every worker thread's malloc arena; glibc raises its mmap threshold after the first
    large free, so later states and activations come from those arenas and the freed space
    between them stays resident. FedLGR at 200 clients (``bench/scale.py``'s lgr-200:
    10,000 scenes at 128 px, two tasks, every client fitting its VAE at each task's end)
    peaked at 4947 MiB without a trim and 3972 MiB with one after each client put to rest
    (~10 ms a trim; VAE fits at 2 epochs, traced in one process); a fixed threshold
    (``MALLOC_MMAP_THRESHOLD_``) held it to 3707 MiB but cost 30 % more time in mmap system
    calls. Hence a trim after each turn of clients put to rest."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@functools.cache
def _malloc_trim():
    try:
        return ctypes.CDLL(None).malloc_trim  # the process's own C library, if glibc
    except (AttributeError, OSError):
        return None


def compact(state: dict, shared: Weights) -> dict:
    """``state`` without the model tensors that equal ``shared``'s (the global ones)."""
    model = {
        k: v
        for k, v in state["model"].items()
        if not (k in shared and v.shape == shared[k].shape and torch.equal(v, shared[k]))
    }
    return {**state, "model": model}


def complete(state: dict, shared: Weights) -> dict:
    """A compact ``state`` with the global tensors it left out (a whole one is unchanged)."""
    return {**state, "model": {**shared, **state["model"]}}


def nbytes_of(value) -> int:
    """The bytes of the tensors in ``value`` (dicts, lists, tuples walked)."""
    if isinstance(value, torch.Tensor):
        return value.numel() * value.element_size()
    if isinstance(value, dict):
        return sum(nbytes_of(v) for v in value.values())
    if isinstance(value, list | tuple):
        return sum(nbytes_of(v) for v in value)
    return 0


class IdleStates:
    """The compact states of the idle clients, by client: in memory while their bytes stay
    within ``budget`` (None: no bound), the others in ``folder`` (one file per client,
    removed when the client is woken). ``elsewhere``: how to keep them elsewhere, said when
    a file cannot be written (a full disk)."""

    def __init__(self, budget: float | None, folder: Path | None, elsewhere: str = ""):
        self.budget, self.folder, self.elsewhere = budget, folder, elsewhere
        self.memory: dict[int, dict] = {}
        self.sizes: dict[int, int] = {}  # of those in memory
        self.on_disk: set[int] = set()
        # clients whose kept state holds global tensors of their own (changed at a task
        # end): a download replaces them (:meth:`download`)
        self.own_shared: set[int] = set()

    def __contains__(self, client: int) -> bool:
        return client in self.memory or client in self.on_disk

    @property
    def held_bytes(self) -> int:
        return sum(self.sizes.values())

    def put(self, client: int, state: dict, shared_keys: set[str]) -> None:
        """Keep ``client``'s compact ``state``; in memory if it fits the budget."""
        if any(k in shared_keys for k in state["model"]):
            self.own_shared.add(client)
        size = nbytes_of(state)
        if self.budget is None or self.held_bytes + size <= self.budget:
            self.memory[client], self.sizes[client] = state, size
            return
        if self.folder is None:
            raise RuntimeError("idle clients spill to disk but no folder was given")
        self.folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        path = self._path(client)
        try:
            save_private(state, path.with_suffix(".tmp"))
        except (OSError, RuntimeError) as err:  # a full disk: torch's writer raises either
            path.with_suffix(".tmp").unlink(missing_ok=True)
            raise FedlgrError(self._unwritten(err)) from None
        os.replace(path.with_suffix(".tmp"), path)
        self.on_disk.add(client)

    def get(self, client: int) -> dict | None:
        """``client``'s kept state (it stays kept); None for a client never put here."""
        if client not in self:
            return None
        if client in self.memory:
            return self.memory[client]
        # our own file, written by :meth:`put`: optimiser and plugin states are not only
        # tensors
        return torch.load(self._path(client), map_location="cpu", weights_only=False)

    def take(self, client: int) -> dict:
        """``client``'s kept state, no longer kept (it is being woken)."""
        state = self.get(client)
        self.memory.pop(client, None)
        self.sizes.pop(client, None)
        self.own_shared.discard(client)
        if client in self.on_disk:
            self.on_disk.discard(client)
            self._path(client).unlink()
        return state

    def download(self, shared_keys: set[str]) -> None:
        """Every idle client takes the new global tensors: a kept state that held global
        tensors of its own no longer does (the woken client gets the new ones)."""
        for client in sorted(self.own_shared):
            state = self.take(client)
            model = {k: v for k, v in state["model"].items() if k not in shared_keys}
            self.put(client, {**state, "model": model}, shared_keys)

    def clear(self) -> None:
        """Forget every kept state (and remove the files)."""
        for client in list(self.on_disk):
            self._path(client).unlink(missing_ok=True)
        self.memory.clear()
        self.sizes.clear()
        self.on_disk.clear()
        self.own_shared.clear()

    def _unwritten(self, err: OSError | RuntimeError) -> str:
        """One line: the folder an idle client's state could not be written in, why, and how
        to keep the states elsewhere."""
        if isinstance(err, OSError) and err.strerror:
            why = err.strerror  # "No space left on device"
        else:  # torch's zip writer says only "unexpected pos" or "basic_ios::clear"
            free = shutil.disk_usage(self.folder).free / 2**20
            why = f"the write failed with {free:.0f} MiB free there"
        return f"cannot write idle clients' states in {self.folder} ({why}); {self.elsewhere}"

    def _path(self, client: int) -> Path:
        assert self.folder is not None
        return self.folder / f"client-{client}.pt"
