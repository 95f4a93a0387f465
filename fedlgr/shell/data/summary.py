"""Readable summaries of a loaded dataset and of its federated split."""

from __future__ import annotations

from fedlgr.core.data.columns import LABEL_SHORT_NAMES
from fedlgr.shell.console import table
from fedlgr.shell.data.dataset import Scenes
from fedlgr.shell.data.splits import FederatedSplit


def describe_scenes(scenes: Scenes) -> str:
    t = scenes.table
    n_circle = int(t.circle.sum())
    head = (
        f"{t.source}: {len(t)} scenes from {int(t.n_ratings.sum())} ratings "
        f"({t.n_ratings.min()}-{t.n_ratings.max()} raters per scene), "
        f"{n_circle} circle / {len(t) - n_circle} arrow"
    )
    if scenes.images is not None:
        _, _, h, w = scenes.images.shape
        head += f", images {w}x{h}"
    targets = scenes.targets
    rows = [
        (
            name,
            float(targets[:, j].mean()),
            float(targets[:, j].std()),
            float(targets[:, j].min()),
            float(targets[:, j].max()),
        )
        for j, name in enumerate(LABEL_SHORT_NAMES)
    ]
    return head + "\n\n" + table(["action", "mean", "sd", "min", "max"], rows)


def describe_split(split: FederatedSplit) -> str:
    tasks = list(split.test_tasks)
    rows = [
        (f"client {c.client}", len(c.train), *(len(c.tasks[k]) for k in tasks))
        for c in split.clients
    ]
    rows.append(("test (shared)", len(split.test), *(len(split.test_tasks[k]) for k in tasks)))
    return table(["shard", "scenes", *(f"task {k}" for k in tasks)], rows)
