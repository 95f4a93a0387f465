"""A dataset folder as per-scene tensors, what every training path reads: the targets and
descriptors from ``all_data.csv``, the images from the decode-once image store."""

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
    check_data_path(Path(config.path))
    return read_ratings(Path(config.path))


def load_scenes(
    config: DataConfig,
    progress: Callable[[int, int], None] | None = None,
    table: SceneTable | None = None,
) -> Scenes:
    """Load ``config.path`` for ``config.modality`` (decoding images at most once);
    ``table``: its :func:`read_table`, where the caller has read it already."""
    table = read_table(config) if table is None else table
    images = None
    if config.modality == "image":
        store = load_image_store(
            Path(config.path) / "images",
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
    """The scenes of ``config`` and their :func:`make_split` (``scheduled``: the tasks every
    client must hold), split before any image is decoded so that a split that cannot be used
    is refused at once; split again where images that failed to decode dropped scenes."""
    table = read_table(config)
    split = make_split(table, config, scheduled)
    scenes = load_scenes(config, progress, table)
    if len(scenes.table) != len(table):
        split = make_split(scenes.table, config, scheduled)
    return scenes, split
