"""Per-round checkpoints of a run: where they live, how they are written and read.

Where: one folder per MLflow run, ``<root>/<run_id>/round-0003.ckpt``, where ``root`` is
``tracking.checkpoint_dir`` if set, else ``checkpoints/`` next to a local sqlite store
(``sqlite:///runs/mlflow.db`` -> ``runs/checkpoints/``), else ``checkpoints/`` in the
working directory (a remote ``mlflow server``). The run's tag ``fedlgr.checkpoints``
records the folder. Not an MLflow artifact: a checkpoint is rewritten every round and
must replace its predecessor atomically (an artifact upload can neither be renamed into
place nor deleted through MLflow's API), and a remote server would receive the full model
of every client every round.

How: rank 0 writes the whole run's state (every client of every process) with Fabric's
``save`` to a temporary name and renames it into place, so a kill during the write leaves
the previous checkpoint intact; it keeps the newest ``tracking.keep_checkpoints`` and
removes the folder when the run finishes. Files are read with ``weights_only=True``:
only tensors and plain Python values, never code (numpy arrays are stored as tensors).
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fedlgr.config import ExperimentConfig, flatten
from fedlgr.errors import FedlgrError

FORMAT = 1
PATTERN = re.compile(r"round-(\d+)\.ckpt")
# Settings a resumed run may change: they do not touch a number the run computes.
SAFE_KEYS = frozenset(
    {
        "runtime.progress",
        "tracking.uri",
        "tracking.checkpoint",
        "tracking.keep_checkpoints",
        "tracking.checkpoint_dir",
        "tracking.system_metrics",
        "tracking.system_metrics_s",
        "data.cache_dir",
    }
)


def checkpoint_root(config: ExperimentConfig, tracking_uri: str) -> Path:
    """The folder that holds the runs' checkpoint folders (see the module docstring)."""
    if config.tracking.checkpoint_dir:
        return Path(config.tracking.checkpoint_dir).expanduser().resolve()
    if tracking_uri.startswith("sqlite:///"):
        return Path(tracking_uri.removeprefix("sqlite:///")).expanduser().resolve().parent / (
            "checkpoints"
        )
    return Path("checkpoints").resolve()


def checkpoints(folder: Path) -> list[Path]:
    """The complete checkpoints in ``folder``, oldest round first (temporary files of an
    interrupted write are not checkpoints)."""
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := PATTERN.fullmatch(p.name))]
    return [p for _, p in sorted(found)]


def save(fabric, folder: Path, round_: int, state: dict[str, Any], keep: int) -> Path | None:
    """Write ``state`` as round ``round_``'s checkpoint (rank 0; every process must call
    this, Fabric's save synchronises them); keep the newest ``keep``."""
    path = folder / f"round-{round_:04d}.ckpt"
    temporary = folder / f".{path.name}.tmp"
    if fabric.global_rank == 0:
        folder.mkdir(parents=True, exist_ok=True)
    fabric.save(temporary, encode(state))
    if fabric.global_rank != 0:
        return None
    os.replace(temporary, path)
    for old in checkpoints(folder)[:-keep]:
        old.unlink(missing_ok=True)
    return path


def write(path: Path, state: dict[str, Any]) -> Path:
    """Write ``state`` to ``path`` atomically, without Fabric (one process: a robot's
    private state between Flower messages); ``load`` reads it back."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    torch.save(encode({"format": FORMAT, **state}), temporary)
    os.replace(temporary, path)
    return path


def load(path: Path) -> dict[str, Any]:
    """A checkpoint's state; a clear error for a file that is not a whole checkpoint."""
    start_over = (
        f"delete it to resume from the previous checkpoint in {path.parent}, or start the run "
        "over without --resume"
    )
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
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
    return decode(state)


def remove(folder: Path) -> None:
    shutil.rmtree(folder, ignore_errors=True)


# --------------------------------------------------------------------------- the config


# Settings a launch may leave to the machine (its cores, its load): a resumed run takes
# its checkpoint's values for them (``resume.adopt_settings``), so that it computes the
# same numbers; they are not part of the fingerprint a run is found by.
MACHINE_CHOSEN = ("runtime.threads", "runtime.concurrency", "runtime.workers")


def fingerprint(config: ExperimentConfig) -> str:
    """A hash of every setting that changes the run's numbers (``SAFE_KEYS`` excluded, and
    the machine-chosen thread settings, which a resume adopts): ``--resume`` without a run
    id, and a sweep's retried trial, look for an unfinished run with the same one."""
    skip = SAFE_KEYS | set(MACHINE_CHOSEN)
    items = sorted((k, v) for k, v in flatten(config).items() if k not in skip)
    return hashlib.sha256(repr(items).encode()).hexdigest()[:16]


def differences(saved: dict[str, str], now: dict[str, str]) -> list[str]:
    """``key (checkpoint A, now B)`` for every setting that differs, safe keys aside."""
    keys = sorted((saved.keys() | now.keys()) - SAFE_KEYS)
    return [
        f"{k} (checkpoint {saved.get(k, 'unset')}, now {now.get(k, 'unset')})"
        for k in keys
        if saved.get(k) != now.get(k)
    ]


# --------------------------------------------------------------------------- encoding

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


def rng_states() -> dict[str, Any]:
    """The process-wide generators (Python, numpy, torch CPU and CUDA)."""
    import random

    return {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }


def set_rng_states(state: dict[str, Any]) -> None:
    import random

    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def to_device(value, device: torch.device):
    """``value`` with every tensor moved to ``device`` (dicts, lists, tuples walked)."""
    if isinstance(value, torch.Tensor):
        # Generator states are CPU byte tensors whatever the device; keep them there.
        return value if value.dtype == torch.uint8 else value.to(device)
    if isinstance(value, dict):
        return {k: to_device(v, device) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(to_device(v, device) for v in value)
    return value
