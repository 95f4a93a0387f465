"""The scenes a run trains on, and how they are split: the core's input data. The shell
reads them from a dataset folder (:mod:`fedlgr.shell.data`); the core indexes them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fedlgr.core.data.columns import FEATURE_COLUMNS, LABEL_COLUMNS, MODE_COLUMNS
from fedlgr.errors import DataError


@dataclass(frozen=True)
class SceneTable:
    """One row per scene (stamp), ratings averaged over the scene's raters."""

    source: Path
    stamps: np.ndarray  # (N,) int64, ascending
    values: dict[str, np.ndarray]  # column name -> (N,) float64 per-scene mean
    n_ratings: np.ndarray  # (N,) int64 raters per scene

    def __len__(self) -> int:
        return len(self.stamps)

    def column(self, name: str) -> np.ndarray:
        if name not in self.values:
            raise DataError(f"{self.source}: no column {name!r} (known: {', '.join(self.values)})")
        return self.values[name]

    @property
    def targets(self) -> np.ndarray:
        """(N, 8) mean Likert rating per action."""
        return np.stack([self.values[c] for c in LABEL_COLUMNS], axis=1)

    @property
    def features(self) -> np.ndarray:
        """(N, 29): the 27 descriptors then the 2 mode flags."""
        return np.stack([self.values[c] for c in FEATURE_COLUMNS], axis=1)

    @property
    def circle(self) -> np.ndarray:
        return self.values[MODE_COLUMNS[0]] == 1.0

    def subset(self, keep: np.ndarray) -> SceneTable:
        return SceneTable(
            self.source,
            self.stamps[keep],
            {k: v[keep] for k, v in self.values.items()},
            self.n_ratings[keep],
        )


@dataclass(frozen=True)
class Scenes:
    """Scenes of one dataset folder, in stamp order."""

    table: SceneTable
    targets: torch.Tensor  # (N, 8) float32, mean Likert rating per action
    features: torch.Tensor  # (N, 29) float32, descriptors + mode flags
    images: torch.Tensor | None  # (N, 3, S, S) uint8, or None for the features modality

    def __len__(self) -> int:
        return len(self.table)

    @property
    def stamps(self) -> np.ndarray:
        return self.table.stamps

    @property
    def inputs(self) -> torch.Tensor:
        """What the root reads: the images if loaded, else the features."""
        return self.images if self.images is not None else self.features

    def subset(self, index: np.ndarray) -> Scenes:
        """The scenes at positions ``index`` (or where a boolean mask is true)."""
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        t = torch.as_tensor(index, dtype=torch.long)
        return Scenes(
            self.table.subset(index),
            self.targets[t],
            self.features[t],
            None if self.images is None else self.images[t],
        )


@dataclass(frozen=True)
class ClientShard:
    client: int
    train: np.ndarray  # positions into the Scenes
    # task name -> positions, a partition of train's task scenes (some may be empty)
    tasks: dict[str, np.ndarray]


@dataclass(frozen=True)
class FederatedSplit:
    train: np.ndarray
    test: np.ndarray
    test_tasks: dict[str, np.ndarray]
    clients: list[ClientShard]
