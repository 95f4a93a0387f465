"""Train/test split, client shards and continual-learning tasks (docs/data.md), as positions
into the scenes, deterministic for a seed; the test set is shared by every client."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from fedlgr.core.data.scenes import ClientShard, FederatedSplit, SceneTable
from fedlgr.errors import ConfigError, DataError
from fedlgr.shell.config import DataConfig, TaskSpec

_DIRICHLET_TRIES = 100
# How long make_split looks for a client count that gives every client every scheduled
# task: an IID split is checked in microseconds per count, a Dirichlet one redraws.
_SEARCH_S = 1.5


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
    """Split the positions ``train`` into ``n_clients`` sorted shards: IID, or each client's
    share of every one of ``groups`` drawn from Dirichlet(``alpha``) (Hsu et al. 2019)."""
    if n_clients > len(train):
        raise ConfigError(
            f"data.clients={n_clients}: more clients than the {len(train)} training scenes"
        )
    if partition == "iid":
        return [np.sort(s) for s in np.array_split(_iid_order(train, seed), n_clients)]
    rng = np.random.default_rng([seed, 2])
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


def _iid_order(train: np.ndarray, seed: int) -> np.ndarray:
    """The training scenes in the order whose consecutive runs are the IID shards: the same
    for every client count."""
    return np.random.default_rng([seed, 2]).permutation(train)


def task_members(table: SceneTable, tasks: tuple[TaskSpec, ...]) -> np.ndarray:
    """For each scene, the position of its task in ``tasks`` (-1: none); overlaps are refused."""
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


def tasks_of(
    positions: np.ndarray, member: np.ndarray, tasks: tuple[TaskSpec, ...]
) -> dict[str, np.ndarray]:
    """The entries of ``positions`` per task (empty for a task it holds none of)."""
    return {task.name: positions[member[positions] == t] for t, task in enumerate(tasks)}


def split_tasks(
    positions: np.ndarray, member: np.ndarray, tasks: tuple[TaskSpec, ...], where: str
) -> dict[str, np.ndarray]:
    """The entries of ``positions`` per task; a task with no scene there is an error."""
    out = tasks_of(positions, member, tasks)
    empty = [name for name, idx in out.items() if len(idx) == 0]
    if empty:
        raise DataError(
            f"{where}: no scenes for task(s) {', '.join(map(repr, empty))} "
            "(see data.tasks, data.clients and data.partition)"
        )
    return out


def _label_quartile(table: SceneTable) -> np.ndarray:
    mean_label = table.targets.mean(axis=1)
    return np.searchsorted(np.quantile(mean_label, [0.25, 0.5, 0.75]), mean_label)


def make_split(
    table: SceneTable, config: DataConfig, scheduled: Sequence[str] = ()
) -> FederatedSplit:
    """Train/test, client shards and per-client tasks for ``config``. The test set must hold
    every task; a client may lack one but those ``scheduled`` (``continual.tasks``: a
    continual-learning schedule trains every client on each of them in turn)."""
    member = task_members(table, config.tasks)
    train, test = train_test_split(member, config.test_fraction, config.seed)
    test_tasks = split_tasks(test, member, config.tasks, "test set")
    groups = (member if config.partition_key == "task" else _label_quartile(table))[train]
    shards = _shards(train, groups, config, config.clients)
    needed = [t for t, task in enumerate(config.tasks) if task.name in scheduled]
    lacking = _lacking(member[np.concatenate(shards)], [len(s) for s in shards], needed)
    if any(lacking):
        names = [config.tasks[t].name for t in needed]
        found, lowest = _most_clients(member, train, groups, config, needed)
        raise ConfigError(_refusal(config, dict(zip(names, lacking, strict=True)), found, lowest))
    clients = [
        ClientShard(c, shard, tasks_of(shard, member, config.tasks))
        for c, shard in enumerate(shards)
    ]
    return FederatedSplit(train, test, test_tasks, clients)


def task_clients(split: FederatedSplit) -> dict[str, int]:
    """For each task, how many clients hold training scenes of it."""
    return {task: sum(len(c.tasks[task]) > 0 for c in split.clients) for task in split.test_tasks}


def _shards(train: np.ndarray, groups: np.ndarray, config: DataConfig, n: int) -> list[np.ndarray]:
    return shard_clients(train, n, config.seed, config.partition, groups, config.dirichlet_alpha)


def _lacking(labels: np.ndarray, sizes: Sequence[int], needed: Sequence[int]) -> list[int]:
    """For each task in ``needed``, how many shards hold none of it. The shards are the
    consecutive runs of ``labels`` (each scene's task) of ``sizes`` (none empty)."""
    starts = np.cumsum([0, *sizes[:-1]])
    return [
        int((np.add.reduceat((labels == t).astype(np.int64), starts) == 0).sum()) for t in needed
    ]


def _most_clients(
    member: np.ndarray, train: np.ndarray, groups: np.ndarray, config: DataConfig, needed
) -> tuple[int | None, int]:
    """The largest client count below ``config.clients`` that gives every client every task in
    ``needed`` (None: none found in ``_SEARCH_S``), and the smallest count tried."""
    stop = time.perf_counter() + _SEARCH_S
    order = member[_iid_order(train, config.seed)]  # the IID shards of any client count
    for n in range(config.clients - 1, 0, -1):
        if config.partition == "iid":
            labels, (q, r) = order, divmod(len(order), n)
            sizes = [q + 1] * r + [q] * (n - r)  # np.array_split's
            if not any(_lacking(labels, sizes, needed)):
                return n, n
        else:
            try:
                shards = _shards(train, groups, config, n)
            except ConfigError:  # every draw left a client without scenes
                shards = []
            sizes = [len(s) for s in shards]
            if shards and not any(_lacking(member[np.concatenate(shards)], sizes, needed)):
                return n, n
        if time.perf_counter() > stop:
            return None, n
    return None, 1


def _refusal(config: DataConfig, lacking: dict[str, int], found: int | None, lowest: int) -> str:
    """One line: how many clients lack which scheduled task, and what would do."""
    counts = sorted(((k, name) for name, k in lacking.items() if k), key=lambda kn: -kn[0])
    (k, name), rest = counts[0], counts[1:]
    parts = [f"{k} client{' holds' if k == 1 else 's hold'} no training scenes of task {name!r}"]
    parts += [f"{k} none of {name!r}" for k, name in rest]
    said = parts[0] if not rest else ", ".join(parts[:-1]) + " and " + parts[-1]
    advice = "use fewer continual.tasks / plain FL" + (
        " / a larger data.dirichlet_alpha" if config.partition == "dirichlet" else ""
    )
    every = f"every client scenes of every task with data.seed={config.seed}"
    if found is not None:
        hint = f"data.clients={found} is the most that give {every}, or {advice}"
    elif lowest > 1:
        hint = (
            f"no data.clients from {config.clients - 1} down to {lowest} gives {every} (the "
            f"search stops after {_SEARCH_S:g} s): try fewer clients, or {advice}"
        )
    else:
        hint = f"no smaller data.clients gives {every}: {advice}"
    return (
        f"data.clients={config.clients}: {said} (continual.tasks needs every client to hold "
        f"each task it trains); {hint}"
    )
