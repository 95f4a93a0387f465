"""Train/test split, client shards and continual-learning tasks (SPEC 2.3).

All functions work on positions into a :class:`~fedlgr.shell.data.dataset.Scenes` and are
deterministic for a seed. The test set is shared by every client.

* ``train_test_split``: 3:1 over scenes, stratified by group (the task by default) so both
  tasks are in the test set in proportion.
* ``shard_clients``: IID equal-size shards (sizes differ by at most one), or non-IID
  shards where each client's share of every group is drawn from Dirichlet(alpha)
  (Hsu et al. 2019): small alpha gives clients dominated by one group.
* ``split_tasks``: the scenes of each task, in the schedule's order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fedlgr.errors import ConfigError, DataError
from fedlgr.shell.config import DataConfig, TaskSpec
from fedlgr.shell.data.ratings import SceneTable

_DIRICHLET_TRIES = 100


def train_test_split(
    groups: np.ndarray, test_fraction: float = 0.25, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Positions of train and test scenes; within each group ``n * test_fraction`` scenes
    (rounded, halves up) go to the test set. Both outputs are sorted."""
    rng = np.random.default_rng([seed, 1])
    train, test = [], []
    for g in np.unique(groups):
        members = rng.permutation(np.flatnonzero(groups == g))
        n_test = int(np.floor(len(members) * test_fraction + 0.5))  # half rounds up
        test.append(members[:n_test])
        train.append(members[n_test:])
    return np.sort(np.concatenate(train)), np.sort(np.concatenate(test))


def shard_clients(
    train: np.ndarray,
    n_clients: int,
    seed: int = 0,
    partition: str = "iid",
    groups: np.ndarray | None = None,
    alpha: float = 0.5,
) -> list[np.ndarray]:
    """Split the positions ``train`` into ``n_clients`` sorted shards.

    ``groups`` (one id per entry of ``train``) is needed for ``partition="dirichlet"``.
    """
    if n_clients > len(train):
        raise ConfigError(
            f"data.clients={n_clients}: more clients than the {len(train)} training scenes"
        )
    rng = np.random.default_rng([seed, 2])
    if partition == "iid":
        return [np.sort(s) for s in np.array_split(rng.permutation(train), n_clients)]
    if groups is None or len(groups) != len(train):
        raise ValueError("dirichlet partition needs one group id per training scene")
    for _ in range(_DIRICHLET_TRIES):
        shards: list[list[int]] = [[] for _ in range(n_clients)]
        for g in np.unique(groups):
            members = rng.permutation(train[groups == g])
            share = rng.dirichlet(np.full(n_clients, alpha))
            cuts = (np.cumsum(share)[:-1] * len(members)).round().astype(int)
            for client, part in enumerate(np.split(members, cuts)):
                shards[client].extend(part.tolist())
        if min(len(s) for s in shards) > 0:
            return [np.sort(np.asarray(s, dtype=np.int64)) for s in shards]
    raise ConfigError(
        f"data.dirichlet_alpha={alpha}: {_DIRICHLET_TRIES} draws each left some of the "
        f"{n_clients} clients without scenes; raise the alpha or lower data.clients"
    )


def task_members(table: SceneTable, tasks: tuple[TaskSpec, ...]) -> np.ndarray:
    """For each scene, the position of its task in ``tasks`` (-1 if it belongs to none).

    A scene matching two tasks is an error: tasks must not overlap.
    """
    member = np.full(len(table), -1, dtype=np.int64)
    for t, task in enumerate(tasks):
        # Values are means over raters: 0.7 averaged over 3 rows is 0.6999999999999998.
        hit = np.isclose(table.column(task.column), task.value, rtol=0.0, atol=1e-6)
        overlap = hit & (member >= 0)
        if overlap.any():
            other = tasks[int(member[overlap][0])].name
            raise ConfigError(
                f"data.tasks: tasks {other!r} and {task.name!r} both contain "
                f"stamp {int(table.stamps[overlap][0])}"
            )
        member[hit] = t
    return member


def split_tasks(
    positions: np.ndarray, member: np.ndarray, tasks: tuple[TaskSpec, ...], where: str
) -> dict[str, np.ndarray]:
    """The entries of ``positions`` per task; a task with no scene there is an error."""
    out = {task.name: positions[member[positions] == t] for t, task in enumerate(tasks)}
    empty = [name for name, idx in out.items() if len(idx) == 0]
    if empty:
        raise DataError(
            f"{where}: no scenes for task(s) {', '.join(map(repr, empty))} "
            "(see data.tasks, data.clients and data.partition)"
        )
    return out


@dataclass(frozen=True)
class ClientShard:
    client: int
    train: np.ndarray  # positions into the Scenes
    tasks: dict[str, np.ndarray]  # task name -> positions, a partition of train's task scenes


@dataclass(frozen=True)
class FederatedSplit:
    train: np.ndarray
    test: np.ndarray
    test_tasks: dict[str, np.ndarray]
    clients: list[ClientShard]


def _label_quartile(table: SceneTable) -> np.ndarray:
    mean_label = table.targets.mean(axis=1)
    return np.searchsorted(np.quantile(mean_label, [0.25, 0.5, 0.75]), mean_label)


def make_split(table: SceneTable, config: DataConfig) -> FederatedSplit:
    """Train/test, client shards and per-client tasks for ``config``, seeded by
    ``config.seed``."""
    member = task_members(table, config.tasks)
    train, test = train_test_split(member, config.test_fraction, config.seed)
    groups = member if config.partition_key == "task" else _label_quartile(table)
    shards = shard_clients(
        train, config.clients, config.seed, config.partition, groups[train], config.dirichlet_alpha
    )
    clients = [
        ClientShard(c, shard, split_tasks(shard, member, config.tasks, f"client {c}"))
        for c, shard in enumerate(shards)
    ]
    return FederatedSplit(train, test, split_tasks(test, member, config.tasks, "test set"), clients)
