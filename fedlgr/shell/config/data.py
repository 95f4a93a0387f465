"""The data settings (``data.*``): where the data is, how it is read, split over clients
and into tasks. Checked on construction by :func:`fedlgr.shell.checks.settings.check_data`
(messages name the setting)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from fedlgr.core.data.columns import USING_ARROW, USING_CIRCLE
from fedlgr.shell.checks.settings import check_data, check_noise, check_task


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
        check_task(self)


DEFAULT_TASKS = (TaskSpec("circle", USING_CIRCLE, 1.0), TaskSpec("arrow", USING_ARROW, 1.0))


@dataclass(frozen=True)
class NoiseConfig:
    """How ``data.augment`` augments the descriptors (``data.modality=features``): each
    training scene becomes ``data.augment_copies`` rows with Gaussian noise on its 27
    descriptors, drawn once (the LEAP-HRI'24 benchmark's augmentation, docs/leap_hri24.md)."""

    std: float = 0.01  # the noise's standard deviation on each descriptor (they span 0..1)
    original: bool = False  # the first copy is the scene itself, without noise
    # copy k carries the sum of k draws (std x sqrt(k)), as the LEAP-HRI'24 code's noise
    # ran; false: every copy its own draw
    cumulative: bool = False

    def __post_init__(self) -> None:
        check_noise(self)


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
    # Images: each training scene shown augment_copies times an epoch, flipped and rotated;
    # descriptors: augment_copies noisy rows per training scene (data.noise)
    augment: bool = False
    augment_copies: int = 10
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "cache_dir", Path(self.cache_dir))
        object.__setattr__(
            self,
            "tasks",
            tuple(t if isinstance(t, TaskSpec) else TaskSpec(**t) for t in self.tasks),
        )
        if not isinstance(self.noise, NoiseConfig):
            object.__setattr__(self, "noise", NoiseConfig(**self.noise))
        check_data(self)
        if self.crop is not None:
            object.__setattr__(self, "crop", tuple(self.crop))
