"""Per-round checkpoints of a run, one folder per MLflow run, not artifacts (a checkpoint replaces
its predecessor atomically, which an upload cannot); read with ``weights_only=True``, never code."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fedlgr.core.state import save_private
from fedlgr.errors import FedlgrError, first_line, interrupt_in
from fedlgr.shell.checks.paths import not_a_folder
from fedlgr.shell.config import ExperimentConfig

FORMAT = 2  # 2: a round's rows name their columns (keys) and participants
PATTERN = re.compile(r"round-(\d+)\.ckpt")
ROOT = "checkpoints"  # the folder of runs' folders, unless tracking.checkpoint_dir names one


def checkpoint_root(config: ExperimentConfig, tracking_uri: str) -> Path:
    """The folder of the runs' checkpoint folders: ``tracking.checkpoint_dir``, else
    ``checkpoints/`` beside a local sqlite store, else in the working directory."""
    if config.tracking.checkpoint_dir:
        given = Path(config.tracking.checkpoint_dir).expanduser()
        # before resolve(): it follows a dangling link, and a link to a device becomes a folder
        if why := not_a_folder(given):
            raise FedlgrError(f"tracking.checkpoint_dir={config.tracking.checkpoint_dir}: {why}")
        return given.resolve()
    if tracking_uri.startswith("sqlite:///"):
        return Path(tracking_uri.removeprefix("sqlite:///")).expanduser().resolve().parent / ROOT
    return Path(ROOT).resolve()


def checkpoints(folder: Path) -> list[Path]:
    """The complete checkpoints in ``folder``, oldest round first (temporary files of an
    interrupted write are not checkpoints)."""
    found = [(int(m.group(1)), p) for p in folder.glob("*") if (m := PATTERN.fullmatch(p.name))]
    return [p for _, p in sorted(found)]


INTERRUPTED = "interrupted"  # what rank 0 tells the others when its write was cut off


def save(fabric, folder: Path, round_: int, state: dict[str, Any], keep: int) -> Path | None:
    """Write ``state`` as round ``round_``'s checkpoint (rank 0; every process calls this and
    waits), keeping the newest ``keep``; ``fabric`` None: a process of its own. Not ``Fabric.save``:
    it stages the file in ``$TMPDIR``, where a kill leaves it and a full disk fails the run."""
    path = folder / f"round-{round_:04d}.ckpt"
    error, interrupt = "", None
    rank, world = (0, 1) if fabric is None else (fabric.global_rank, fabric.world_size)
    if rank == 0:
        try:
            _write_atomically(path, encode(state))
        except (OSError, RuntimeError) as err:  # torch.save wraps a failed write in the latter
            # and a Ctrl-C or SIGTERM in the middle of its writes too: that is no I/O error
            interrupt = interrupt_in(err)
            error = f"cannot write checkpoint {path}: {_io_reason(err)}"
            error = INTERRUPTED if interrupt is not None else error
    if world > 1:
        error = fabric.broadcast(error, src=0)
    if error == INTERRUPTED:  # every process stops as rank 0 does
        raise interrupt or KeyboardInterrupt() from None
    if error:
        raise FedlgrError(
            f"{error}; free space or choose another folder (tracking.checkpoint_dir=...), "
            "then --resume (the checkpoints before it are intact)"
        )
    if rank != 0:
        return None
    for old in checkpoints(folder)[:-keep]:
        old.unlink(missing_ok=True)
    return path


def _io_reason(err: BaseException) -> str:
    """The operating system's reason inside ``err`` ("No space left on device")."""
    seen = err
    while seen is not None:
        if isinstance(seen, OSError) and seen.strerror:
            return seen.strerror
        seen = seen.__cause__ or seen.__context__
    return first_line(err, 200)


def _write_atomically(path: Path, state: Any) -> None:
    """``torch.save`` to a temporary name in ``path``'s own folder, then rename: a kill
    leaves the previous file intact and the temporary where the next start removes it."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    try:
        save_private(state, temporary, durable=True)
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def remove_temporaries(folder: Path) -> list[Path]:
    """Remove what interrupted writes left in ``folder``; the files removed."""
    stale = list(folder.glob(".round-*.ckpt.tmp"))
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def write(path: Path, state: dict[str, Any]) -> Path:
    """Write ``state`` to ``path`` atomically, without Fabric (one process: a robot's
    private state between Flower messages); ``load`` reads it back."""
    _write_atomically(path, encode({"format": FORMAT, **state}))
    return path


RUN_KEYS = ("run_id", "round", "config", "server", "clients", "rng", "rows", "elapsed")


def load(path: Path, required: tuple[str, ...] = ()) -> dict[str, Any]:
    """A checkpoint's state; a clear error for a file that is not a whole checkpoint
    (``required``: the keys it must hold, e.g. ``RUN_KEYS`` for a run's checkpoint)."""
    start_over = (
        f"delete it to resume from the previous checkpoint in {path.parent}, or start the run "
        "over without --resume"
    )
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        reason = first_line(err)
        if "Weights only load failed" in reason:
            reason = "it holds objects other than tensors and plain values"
        raise FedlgrError(
            f"{path}: not a readable fedlgr checkpoint ({reason[:200]}); {start_over}"
        ) from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        found = state.get("format") if isinstance(state, dict) else type(state).__name__
        raise FedlgrError(
            f"{path}: not a fedlgr checkpoint of format {FORMAT} (found {found!r}); {start_over}"
        )
    if missing := [k for k in required if k not in state]:
        missed = ", ".join(missing)
        raise FedlgrError(f"{path}: an incomplete checkpoint (no {missed}); {start_over}")
    return decode(state)


def remove(folder: Path, ours: bool = False) -> None:
    """Remove a run's checkpoint folder, and the folder of runs' folders if left empty and ``ours``
    (fedlgr's own ``checkpoints/``, not a ``tracking.checkpoint_dir`` the user made)."""
    shutil.rmtree(folder, ignore_errors=True)
    if ours and folder.parent.name == ROOT:
        with contextlib.suppress(OSError):  # not empty, or another run made it meanwhile
            folder.parent.rmdir()


_ARRAY = "__ndarray__"


def encode(value: Any) -> Any:
    """numpy arrays -> ``{"__ndarray__": tensor}``, numpy scalars -> Python numbers, so
    that ``torch.load(weights_only=True)`` reads the file back."""
    if isinstance(value, np.ndarray):
        return {_ARRAY: torch.from_numpy(np.ascontiguousarray(value))}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {k: encode(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(encode(v) for v in value)
    return value


def decode(value: Any) -> Any:
    if isinstance(value, dict):
        if value.keys() == {_ARRAY}:
            return value[_ARRAY].numpy()
        return {k: decode(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(decode(v) for v in value)
    return value
