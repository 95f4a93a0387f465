"""Data settings: one typed dataclass, validated on construction (messages name the setting)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from fedlgr.core.data.columns import USING_ARROW, USING_CIRCLE
from fedlgr.errors import ConfigError
from fedlgr.shell.checks.values import check_numbers, check_seed, choice, format_bytes

MODALITIES = ("image", "features")
PARTITIONS = ("iid", "dirichlet")
PARTITION_KEYS = ("task", "label")
BAD_IMAGE_POLICIES = ("error", "skip")
# Bounds on purpose (each message says why): the paper trains at 128 px with 10 copies of
# each scene per epoch.
MIN_IMAGE_SIZE, MAX_IMAGE_SIZE = 16, 4096
MAX_AUGMENT_COPIES = 1000


def default_cache_dir() -> Path:
    """``$FEDLGR_CACHE_DIR``, else ``$XDG_CACHE_HOME/fedlgr``, else ``~/.cache/fedlgr``."""
    if "FEDLGR_CACHE_DIR" in os.environ:
        return Path(os.environ["FEDLGR_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "fedlgr"


def cache_dir_setting(cache_dir: Path) -> str:
    """The name of the setting that chose ``cache_dir``, for error messages."""
    from_env = os.environ.get("FEDLGR_CACHE_DIR")
    return "FEDLGR_CACHE_DIR" if from_env and Path(from_env) == cache_dir else "data.cache_dir"


@dataclass(frozen=True)
class TaskSpec:
    """A continual-learning task: the scenes whose ``column`` equals ``value``."""

    name: str
    column: str
    value: float = 1.0

    def __post_init__(self) -> None:
        check_numbers(f"data.tasks.{self.name}.", self)


DEFAULT_TASKS = (TaskSpec("circle", USING_CIRCLE, 1.0), TaskSpec("arrow", USING_ARROW, 1.0))


@dataclass(frozen=True)
class DataConfig:
    """Where the data is, how it is read, split over clients and into tasks.

    ``crop`` is ``(left, top, right, bottom)`` in source pixels, applied before resizing;
    ``None`` in a position means that image edge (MANNERS-DB renders: ``(295, None, 1313,
    None)``). ``partition="dirichlet"`` draws each client's share of every group (the
    scene's task, or its mean-label quartile) from Dirichlet(``dirichlet_alpha``).
    """

    path: Path = Path("data/manners-synth")
    modality: str = "image"
    image_size: int = 128
    crop: tuple[int | None, int | None, int | None, int | None] | None = None
    on_bad_image: str = "error"
    cache: bool = True
    cache_dir: Path = field(default_factory=default_cache_dir)
    test_fraction: float = 0.25
    clients: int = 2
    partition: str = "iid"
    dirichlet_alpha: float = 0.5
    partition_key: str = "task"
    tasks: tuple[TaskSpec, ...] = DEFAULT_TASKS
    augment: bool = False
    augment_copies: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "cache_dir", Path(self.cache_dir))
        object.__setattr__(
            self,
            "tasks",
            tuple(t if isinstance(t, TaskSpec) else TaskSpec(**t) for t in self.tasks),
        )
        check_numbers("data.", self)
        check_seed("data.seed", self.seed)
        choice("data.modality", self.modality, MODALITIES)
        choice("data.partition", self.partition, PARTITIONS)
        choice("data.partition_key", self.partition_key, PARTITION_KEYS)
        choice("data.on_bad_image", self.on_bad_image, BAD_IMAGE_POLICIES)
        size = self.image_size
        if size < MIN_IMAGE_SIZE:
            raise ConfigError(f"data.image_size={size}: must be at least {MIN_IMAGE_SIZE}")
        if size > MAX_IMAGE_SIZE:
            raise ConfigError(
                f"data.image_size={size}: at most {MAX_IMAGE_SIZE} (a fixed bound: each scene "
                f"takes 3 x size^2 bytes in the decoded image store and 12 x size^2 as float32 in "
                f"a batch, {format_bytes(3 * size**2)} and {format_bytes(12 * size**2)} here; "
                "the paper trains at 128 px)"
            )
        if not 0.0 < self.test_fraction < 1.0:
            raise ConfigError(f"data.test_fraction={self.test_fraction}: must be between 0 and 1")
        if self.clients < 1:
            raise ConfigError(f"data.clients={self.clients}: need at least 1 client")
        if self.dirichlet_alpha <= 0:
            raise ConfigError(f"data.dirichlet_alpha={self.dirichlet_alpha}: must be > 0")
        copies = self.augment_copies
        if copies < 1:
            raise ConfigError(f"data.augment_copies={copies}: must be >= 1")
        if copies > MAX_AUGMENT_COPIES:
            raise ConfigError(
                f"data.augment_copies={copies}: at most {MAX_AUGMENT_COPIES} (a fixed bound: an "
                "augmented epoch shows each training scene this many times, and its shuffled "
                f"order takes 24 bytes per showing, {format_bytes(24 * copies)} per scene here; "
                "the paper uses 10)"
            )
        if not self.tasks:
            raise ConfigError("data.tasks: need at least one task")
        names = [t.name for t in self.tasks]
        if len(set(names)) != len(names):
            raise ConfigError(f"data.tasks: task names must be unique, got {names}")
        if self.crop is not None:
            object.__setattr__(self, "crop", _crop(self.crop))


def _crop(crop) -> tuple[int | None, int | None, int | None, int | None]:
    box = tuple(crop)
    if len(box) != 4 or not all(v is None or (isinstance(v, int) and v >= 0) for v in box):
        raise ConfigError(
            f"data.crop={list(crop)}: must be [left, top, right, bottom] "
            "pixel positions (>= 0) or null for an image edge"
        )
    left, top, right, bottom = box
    if left is not None and right is not None and right <= left:
        raise ConfigError(f"data.crop={list(crop)}: right ({right}) must exceed left ({left})")
    if top is not None and bottom is not None and bottom <= top:
        raise ConfigError(f"data.crop={list(crop)}: bottom ({bottom}) must exceed top ({top})")
    return box  # type: ignore[return-value]
