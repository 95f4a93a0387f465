"""A loaded config written out (plain values, YAML, flat names) and the hash of the settings that
change a run's numbers; what is written out never holds the password of ``tracking.uri``."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Any

import yaml

from fedlgr.core.declare import settings_of
from fedlgr.core.settings import ExperimentConfig
from fedlgr.shell.tracking.uri import mask_password


def to_plain(value: Any) -> Any:
    """Dataclasses -> dicts, tuples -> lists, paths -> strings (YAML/MLflow friendly)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, list | tuple):
        return [to_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: to_plain(v) for k, v in value.items()}
    if isinstance(value, Path):
        return str(value)
    return value


def to_yaml(config: ExperimentConfig) -> str:
    """The resolved config as YAML (``--print-config``, the run's ``config.yaml``), the password of
    ``tracking.uri`` masked: the UI shows the artifact to whoever opens the run."""
    plain = to_plain(config)
    if plain["tracking"]["uri"]:
        plain["tracking"]["uri"] = mask_password(str(plain["tracking"]["uri"]))
    return yaml.safe_dump(plain, sort_keys=False)


def robot_yaml(config: ExperimentConfig) -> str:
    """The resolved config as a Flower server sends it to its robots: :func:`to_yaml` without
    ``tracking.uri``, since the store's address is the server's alone."""
    plain = to_plain(config)
    plain["tracking"]["uri"] = None
    return yaml.safe_dump(plain, sort_keys=False)


def flatten(config: ExperimentConfig) -> dict[str, str]:
    """``{"data.clients": "2", ...}``: the resolved config as MLflow params and as a
    checkpoint keeps it, the password of ``tracking.uri`` masked."""
    out = {key: str(value) for key, value in _leaves(to_plain(config))}
    if out.get("tracking.uri"):  # what is kept (checkpoints) holds no password
        out["tracking.uri"] = mask_password(out["tracking.uri"])
    return out


def _leaves(values: dict, prefix: str = ""):
    """``(dotted name, value)`` for every setting (not section) in plain ``values``."""
    for key, value in values.items():
        if isinstance(value, dict):
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def short_setting(name: str) -> str:
    """A setting without its section, for names of trials and cells: ``train.lr_root`` ->
    ``lr_root``, ``continual.lgr.replay`` -> ``lgr.replay``."""
    return name.split(".", 1)[-1]


def known_settings() -> list[str]:
    """Every setting's dotted name (``train.lr_top``, ...)."""
    return [name for name, _, _ in settings_of(ExperimentConfig)]


# --------------------------------------------------------------------------- what changes a run

# Settings a resumed run may change: they do not touch a number the run computes.
SAFE_KEYS = frozenset(
    {
        "runtime.progress",
        "runtime.timeout_s",
        "runtime.idle_clients",  # where idle clients wait: the same numbers either way
        "runtime.idle_memory_mb",
        "tracking.uri",
        "tracking.checkpoint",
        "tracking.keep_checkpoints",
        "tracking.checkpoint_dir",
        "tracking.system_metrics",
        "tracking.system_metrics_s",
        "data.cache_dir",
    }
)

# Settings a launch may leave to the machine: a resumed run adopts its checkpoint's values
# (``resume.adopted``) to compute the same numbers, so they are not hashed.
MACHINE_CHOSEN = ("runtime.threads", "runtime.concurrency", "runtime.workers")


def config_hash(config: ExperimentConfig) -> str:
    """A hash of every setting that changes the run's numbers (not ``SAFE_KEYS`` nor
    ``MACHINE_CHOSEN``): ``--resume`` without a run id and a sweep's retried trial look for an
    unfinished run with the same one."""
    skip = SAFE_KEYS | set(MACHINE_CHOSEN)
    items = sorted((k, v) for k, v in flatten(config).items() if k not in skip)
    return hashlib.sha256(repr(items).encode()).hexdigest()[:16]
