"""Readable summaries of a loaded dataset and of its federated split."""

from __future__ import annotations

import numpy as np

from fedlgr.core.data.columns import LABEL_SHORT_NAMES
from fedlgr.core.data.scenes import FederatedSplit, Scenes
from fedlgr.shell.console import table


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


def describe_split(split: FederatedSplit, most: int = 20) -> str:
    """One row per client and one for the shared test set; over ``most`` clients, the first
    ``most // 2`` rows and the scenes per client (min, median, max, clients with none)."""
    tasks = list(split.test_tasks)
    clients = split.clients
    shown = clients if len(clients) <= most else clients[: most // 2]
    rows = [(f"client {c.client}", len(c.train), *(len(c.tasks[k]) for k in tasks)) for c in shown]
    if len(shown) < len(clients):
        rows.append((f"({len(clients) - len(shown)} more clients)", *[""] * (1 + len(tasks))))
    rows.append(("test (shared)", len(split.test), *(len(split.test_tasks[k]) for k in tasks)))
    headers = ["shard", "scenes", *(f"task {k}" for k in tasks)]
    out = table(headers, rows)
    if len(shown) == len(clients):
        return out
    sizes = np.array([[len(c.train), *(len(c.tasks[k]) for k in tasks)] for c in clients])
    summary = [
        ("min", *sizes.min(axis=0)),
        ("median", *(f"{m:g}" for m in np.median(sizes, axis=0))),
        ("max", *sizes.max(axis=0)),
        ("clients with none", *(sizes == 0).sum(axis=0)),
    ]
    return f"{out}\n\nper client, over all {len(clients)} clients:\n" + table(
        ["", *headers[1:]], summary
    )
