"""A dataset folder as per-scene tensors: what every training path reads.

``load_scenes(config)`` reads ``all_data.csv`` (validated, ratings averaged per stamp) and,
for the image modality, the decode-once image store. The result holds, in stamp order,
the targets (mean rating of the 8 actions), the features-modality inputs (27 descriptors
+ 2 mode flags) and, for images, a uint8 ``(N, 3, S, S)`` tensor. ``load_split`` also
splits them, from the CSV before any image is decoded, so a split that cannot be used is
refused in a moment.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from fedlgr.core.data.scenes import Scenes, SceneTable
from fedlgr.shell.checks.paths import check_data_path
from fedlgr.shell.config import DataConfig
from fedlgr.shell.data.images import load_image_store
from fedlgr.shell.data.ratings import read_ratings
from fedlgr.shell.data.splits import FederatedSplit, make_split


def read_table(config: DataConfig) -> SceneTable:
    """The scenes of ``config.path``'s ``all_data.csv``: what a split is made of, read in
    a moment where decoding the images takes minutes."""
    return read_ratings(_dataset_folder(Path(config.path)))


def load_scenes(
    config: DataConfig,
    progress: Callable[[int, int], None] | None = None,
    table: SceneTable | None = None,
) -> Scenes:
    """Load ``config.path`` for ``config.modality`` (decoding images at most once);
    ``table``: its :func:`read_table`, where the caller has read it already."""
    folder = _dataset_folder(Path(config.path))
    table = read_ratings(folder) if table is None else table
    images = None
    if config.modality == "image":
        store = load_image_store(
            folder / "images",
            table.stamps,
            config.image_size,
            config.crop,
            config.on_bad_image,
            config.cache_dir if config.cache else None,
            progress,
        )
        if len(store.stamps) != len(table):  # scenes skipped for want of a usable image
            table = table.subset(np.isin(table.stamps, store.stamps))
        images = store.images
    return Scenes(
        table,
        torch.as_tensor(table.targets, dtype=torch.float32),
        torch.as_tensor(table.features, dtype=torch.float32),
        images,
    )


def load_split(
    config: DataConfig,
    scheduled: Sequence[str] = (),
    progress: Callable[[int, int], None] | None = None,
) -> tuple[Scenes, FederatedSplit]:
    """The scenes of ``config`` and their :func:`make_split` (``scheduled``: the tasks
    every client must hold). The split is made from ``all_data.csv`` before any image is
    decoded, so a split that cannot be used is refused in a moment; it is made again
    where images that failed to decode dropped scenes."""
    table = read_table(config)
    split = make_split(table, config, scheduled)
    scenes = load_scenes(config, progress, table)
    if len(scenes.table) != len(table):
        split = make_split(scenes.table, config, scheduled)
    return scenes, split


def _dataset_folder(path: Path) -> Path:
    """``path`` itself, refused when it is not a folder (:func:`check_data_path`)."""
    check_data_path(path)
    return path
