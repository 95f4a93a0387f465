"""Train/test split, client shards and tasks (fedlgr/shell/data/splits.py) on hand-checked data."""

from __future__ import annotations

import dataclasses
import re
import time
from pathlib import Path

import mlflow
import numpy as np
import pytest

import fedlgr.shell.data.dataset as dataset_module
import fedlgr.shell.data.images as images_module
from fedlgr.core.data.columns import (
    DESCRIPTOR_COLUMNS,
    LABEL_COLUMNS,
    MODE_COLUMNS,
    USING_ARROW,
    USING_CIRCLE,
)
from fedlgr.core.data.scenes import SceneTable
from fedlgr.errors import ConfigError, DataError
from fedlgr.shell.cli import main
from fedlgr.shell.config import DEFAULT_TASKS, DataConfig, TaskSpec
from fedlgr.shell.data import splits
from fedlgr.shell.data.ratings import read_ratings
from fedlgr.shell.data.splits import (
    make_split,
    shard_clients,
    split_tasks,
    task_clients,
    task_members,
    train_test_split,
)
from tests.support.data import HEADER, rating_row, write_rows
from tests.support.runs import FAST

MUSIC = "Music playing?"


def make_table(
    circle: np.ndarray, music: np.ndarray | None = None, first_stamp: int = 250
) -> SceneTable:
    """A SceneTable with one scene per entry of ``circle`` (stamps from ``first_stamp``)."""
    circle = np.asarray(circle, dtype=bool)
    n = len(circle)
    values = {c: np.full(n, 0.5) for c in DESCRIPTOR_COLUMNS}
    values[MUSIC] = np.zeros(n) if music is None else np.asarray(music, dtype=float)
    values[MODE_COLUMNS[0]] = circle.astype(float)
    values[MODE_COLUMNS[1]] = (~circle).astype(float)
    for j, c in enumerate(LABEL_COLUMNS):
        values[c] = 1.0 + (np.arange(n) * (j + 1)) % 5
    stamps = first_stamp + np.arange(n, dtype=np.int64)
    return SceneTable(Path("table.csv"), stamps, values, np.full(n, 4, dtype=np.int64))


def assert_partition(parts, whole) -> None:
    """``parts`` are sorted, pairwise disjoint, and together exactly ``whole``."""
    joined = np.concatenate([np.asarray(p) for p in parts])
    assert len(joined) == len(np.unique(joined)), "parts overlap"
    assert np.array_equal(np.sort(joined), np.sort(np.asarray(whole)))
    for p in parts:
        assert np.all(np.diff(p) > 0), "a part is not sorted"


# --- train_test_split --------------------------------------------------------------------

# Group sizes 12, 7, 5, 10, 6: test counts n/4 rounded half up = 3, 2, 1, 3 (2.5 -> 3), 2.
GROUP_SIZES = {0: 12, 1: 7, 2: 5, 3: 10, 4: 6}


def half_up(x: float) -> int:
    return int(np.floor(x + 0.5))


def interleaved_groups() -> np.ndarray:
    groups = np.concatenate([np.full(n, g) for g, n in GROUP_SIZES.items()])
    return np.random.default_rng(123).permutation(groups)


def test_train_test_split_is_a_stratified_partition():
    groups = interleaved_groups()
    train, test = train_test_split(groups, 0.25, seed=0)
    assert_partition([train, test], np.arange(len(groups)))
    assert len(test) == 3 + 2 + 1 + 3 + 2
    for g, n in GROUP_SIZES.items():
        assert np.sum(groups[test] == g) == half_up(n * 0.25)
        assert np.sum(groups[train] == g) == n - half_up(n * 0.25)


def test_train_test_split_other_fraction():
    groups = np.repeat([0, 1], [20, 8])
    train, test = train_test_split(groups, 0.5, seed=3)
    assert np.sum(groups[test] == 0) == 10 and np.sum(groups[test] == 1) == 4
    assert_partition([train, test], np.arange(28))


def test_train_test_split_is_seeded():
    groups = interleaved_groups()
    a, b = train_test_split(groups, seed=5), train_test_split(groups, seed=5)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    c = train_test_split(groups, seed=6)
    assert not np.array_equal(a[1], c[1])
    # The stratified counts do not depend on the seed.
    assert len(c[1]) == len(a[1])


# --- shard_clients: iid ------------------------------------------------------------------


def test_iid_shards_are_balanced_disjoint_and_complete():
    train = np.arange(3, 49, 2)  # 23 non-contiguous positions
    shards = shard_clients(train, 5, seed=0)
    assert len(shards) == 5
    assert sorted(len(s) for s in shards) == [4, 4, 5, 5, 5]
    assert_partition(shards, train)
    for s in shards:
        assert s.dtype.kind == "i"


def test_iid_one_client_gets_everything_and_one_scene_per_client_works():
    train = np.array([2, 9, 4, 7])
    (only,) = shard_clients(train, 1)
    assert np.array_equal(only, [2, 4, 7, 9])
    shards = shard_clients(train, 4, seed=1)
    assert [len(s) for s in shards] == [1, 1, 1, 1]
    assert_partition(shards, train)


def test_iid_shards_are_seeded():
    train = np.arange(40)
    a, b = shard_clients(train, 3, seed=4), shard_clients(train, 3, seed=4)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    c = shard_clients(train, 3, seed=5)
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))


def test_more_clients_than_training_scenes_is_a_config_error():
    with pytest.raises(ConfigError, match=r"data\.clients=6") as err:
        shard_clients(np.arange(5), 6)
    assert "5 training scenes" in str(err.value)
    with pytest.raises(ConfigError, match=r"data\.clients"):
        shard_clients(np.arange(5), 6, partition="dirichlet", groups=np.zeros(5, int))


# --- shard_clients: dirichlet ------------------------------------------------------------


def two_groups_of_20() -> tuple[np.ndarray, np.ndarray]:
    """40 training positions (100..139), 20 in group 0 and 20 in group 1, interleaved."""
    train = 100 + np.arange(40)
    groups = np.random.default_rng(9).permutation(np.repeat([0, 1], 20))
    return train, groups


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dirichlet_huge_alpha_splits_every_group_evenly(seed):
    train, groups = two_groups_of_20()
    shards = shard_clients(train, 2, seed, "dirichlet", groups, alpha=1e6)
    assert_partition(shards, train)
    group_of = dict(zip(train.tolist(), groups.tolist(), strict=True))
    for s in shards:
        g = np.array([group_of[p] for p in s.tolist()])
        assert np.sum(g == 0) == 10 and np.sum(g == 1) == 10


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_dirichlet_tiny_alpha_gives_each_client_a_single_group(seed):
    train, groups = two_groups_of_20()
    shards = shard_clients(train, 2, seed, "dirichlet", groups, alpha=1e-3)
    assert all(len(s) > 0 for s in shards)
    assert_partition(shards, train)
    group_of = dict(zip(train.tolist(), groups.tolist(), strict=True))
    owned = [{group_of[p] for p in s.tolist()} for s in shards]
    assert all(len(o) == 1 for o in owned)
    assert owned[0] != owned[1]  # both non-empty, so the two groups went to different clients
    assert sorted(len(s) for s in shards) == [20, 20]


def test_dirichlet_shards_are_seeded_and_non_empty():
    train = np.arange(60)
    groups = np.arange(60) % 3
    a = shard_clients(train, 4, 7, "dirichlet", groups, alpha=0.5)
    b = shard_clients(train, 4, 7, "dirichlet", groups, alpha=0.5)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert all(len(s) > 0 for s in a)
    assert_partition(a, train)
    c = shard_clients(train, 4, 8, "dirichlet", groups, alpha=0.5)
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))


def test_impossible_dirichlet_is_a_config_error():
    # One group and alpha ~ 0: every draw hands the whole group to a single client.
    with pytest.raises(ConfigError, match=r"data\.dirichlet_alpha=0\.001") as err:
        shard_clients(np.arange(30), 3, 0, "dirichlet", np.zeros(30, int), alpha=1e-3)
    assert "3 clients" in str(err.value)


def test_dirichlet_needs_one_group_per_training_scene():
    with pytest.raises(ValueError, match="group id"):
        shard_clients(np.arange(10), 2, partition="dirichlet")
    with pytest.raises(ValueError, match="group id"):
        shard_clients(np.arange(10), 2, partition="dirichlet", groups=np.zeros(9, int))


# --- task_members / split_tasks ----------------------------------------------------------

CIRCLE = np.array([1, 0, 0, 1, 1, 0, 1, 0, 0, 0, 1, 1], dtype=bool)


def test_default_tasks_are_circle_then_arrow():
    assert [(t.name, t.column, t.value) for t in DEFAULT_TASKS] == [
        ("circle", USING_CIRCLE, 1.0),
        ("arrow", USING_ARROW, 1.0),
    ]
    assert DataConfig().tasks == DEFAULT_TASKS


def test_task_members_of_default_tasks():
    table = make_table(CIRCLE)
    member = task_members(table, DEFAULT_TASKS)
    assert member.dtype == np.int64
    assert np.array_equal(member, np.where(CIRCLE, 0, 1))


def test_split_tasks_partitions_each_shard():
    table = make_table(CIRCLE)
    member = task_members(table, DEFAULT_TASKS)
    shard = np.array([0, 1, 2, 4, 6, 9, 11])
    tasks = split_tasks(shard, member, DEFAULT_TASKS, "client 0")
    assert list(tasks) == ["circle", "arrow"]
    assert np.array_equal(tasks["circle"], [0, 4, 6, 11])
    assert np.array_equal(tasks["arrow"], [1, 2, 9])
    assert_partition(tasks.values(), shard)


def test_scenes_in_no_task_are_minus_one_and_left_out():
    table = make_table(CIRCLE, music=np.array([1, 0] * 6))
    tasks = (TaskSpec("music", MUSIC, 1.0),)
    member = task_members(table, tasks)
    assert np.array_equal(member, np.where(np.arange(12) % 2 == 0, 0, -1))
    out = split_tasks(np.arange(12), member, tasks, "test set")
    assert np.array_equal(out["music"], np.arange(0, 12, 2))


def test_overlapping_tasks_are_a_config_error_naming_both():
    music = np.zeros(12)
    music[4] = 1.0  # scene 4 (stamp 254) is a circle scene with music
    table = make_table(CIRCLE, music=music)
    tasks = (TaskSpec("round", USING_CIRCLE, 1.0), TaskSpec("loud", MUSIC, 1.0))
    with pytest.raises(ConfigError, match=r"data\.tasks") as err:
        task_members(table, tasks)
    message = str(err.value)
    assert "'round'" in message and "'loud'" in message and "stamp 254" in message


def test_task_on_an_unknown_column_is_a_data_error():
    with pytest.raises(DataError, match="no column 'Nope'"):
        task_members(make_table(CIRCLE), (TaskSpec("x", "Nope", 1.0),))


def test_shard_without_scenes_of_a_task_is_a_data_error_naming_client_and_task():
    member = task_members(make_table(CIRCLE), DEFAULT_TASKS)
    only_circle = np.flatnonzero(CIRCLE)
    with pytest.raises(DataError, match="client 3") as err:
        split_tasks(only_circle, member, DEFAULT_TASKS, "client 3")
    assert "'arrow'" in str(err.value) and "'circle'" not in str(err.value)


# --- small shards: a client without a task --------------------------------------------

BOTH = ("circle", "arrow")  # the FCL schedule of the default tasks
RULE = "(continual.tasks needs every client to hold each task it trains)"


def test_plain_fl_lets_a_client_hold_no_training_scenes_of_a_task():
    # Dirichlet over the task with alpha ~ 0: each client holds one task only.
    table = make_table(np.arange(40) % 2 == 0)
    config = DataConfig(clients=2, partition="dirichlet", dirichlet_alpha=1e-3)
    split = make_split(table, config)
    held = [{k for k, idx in c.tasks.items() if len(idx)} for c in split.clients]
    assert sorted(map(sorted, held)) == [["arrow"], ["circle"]]
    for c in split.clients:
        assert_partition([idx for idx in c.tasks.values() if len(idx)], c.train)
    assert task_clients(split) == {"circle": 1, "arrow": 1}
    assert {k: len(v) for k, v in split.test_tasks.items()} == {"circle": 5, "arrow": 5}


def test_a_client_without_a_scheduled_task_is_refused_with_the_clients_that_would_do():
    table = make_table(np.arange(40) % 2 == 0)
    config = DataConfig(clients=2, partition="dirichlet", dirichlet_alpha=1e-3)
    with pytest.raises(ConfigError) as caught:
        make_split(table, config, BOTH)
    assert str(caught.value) == (
        f"data.clients=2: 1 client holds no training scenes of task 'circle' and 1 none of "
        f"'arrow' {RULE}; data.clients=1 is the most that give every client scenes of every "
        "task with data.seed=0, or use fewer continual.tasks / plain FL / a larger "
        "data.dirichlet_alpha"
    )


def test_only_the_scheduled_tasks_must_be_held_by_every_client():
    # 36 circle and 4 arrow scenes: 27 and 3 of them train, over 6 IID clients of 5 scenes,
    # so every client holds circle scenes and at least 3 hold no arrow scene.
    table = make_table(np.arange(40) >= 4)
    config = DataConfig(clients=6, seed=3)
    plain = make_split(table, config)
    lacking = 6 - task_clients(plain)["arrow"]
    assert task_clients(plain)["circle"] == 6 and lacking >= 3
    circle_only = make_split(table, config, ("circle",))
    assert all(
        np.array_equal(a.train, b.train)
        for a, b in zip(plain.clients, circle_only.clients, strict=True)
    )
    with pytest.raises(ConfigError) as caught:
        make_split(table, config, ("arrow",))
    message = str(caught.value)
    found = re.fullmatch(
        rf"data\.clients=6: {lacking} clients hold no training scenes of task 'arrow' "
        rf"{re.escape(RULE)}; data\.clients=(\d) is the most that give every client scenes "
        r"of every task with data\.seed=3, or use fewer continual\.tasks / plain FL",
        message,
    )
    assert found, message
    most = int(found.group(1))
    assert 1 <= most <= 3  # 3 arrow scenes train
    split = make_split(table, dataclasses.replace(config, clients=most), ("arrow",))
    assert all(len(c.tasks["arrow"]) for c in split.clients)
    for clients in range(most + 1, 6):  # every count above it leaves a client without
        fewer = dataclasses.replace(config, clients=clients)
        assert task_clients(make_split(table, fewer))["arrow"] < clients
        with pytest.raises(ConfigError, match=f"^data.clients={clients}: "):
            make_split(table, fewer, ("arrow",))


def test_where_no_client_count_gives_every_client_a_task_it_is_said():
    # 2 arrow scenes, both in the test set at test_fraction 0.9: no client can train on one.
    table = make_table(np.arange(40) >= 2)
    config = DataConfig(clients=2, test_fraction=0.9)
    assert task_clients(make_split(table, config)) == {"circle": 2, "arrow": 0}
    with pytest.raises(ConfigError) as caught:
        make_split(table, config, BOTH)
    assert str(caught.value) == (
        f"data.clients=2: 2 clients hold no training scenes of task 'arrow' {RULE}; no smaller "
        "data.clients gives every client scenes of every task with data.seed=0: use fewer "
        "continual.tasks / plain FL"
    )


def test_the_search_for_a_client_count_stops_after_its_time(monkeypatch):
    monkeypatch.setattr(splits, "_SEARCH_S", 0.0)  # stops after the first count it tries
    table = make_table(np.arange(400) % 2 == 0)
    with pytest.raises(ConfigError) as caught:
        make_split(table, DataConfig(clients=300), BOTH)
    assert re.fullmatch(
        rf"data\.clients=300: \d+ clients hold no training scenes of task '\w+' and \d+ none "
        rf"of '\w+' {re.escape(RULE)}; no data\.clients from 299 down to 299 gives every "
        r"client scenes of every task with data\.seed=0 \(the search stops after 0 s\): try "
        r"fewer clients, or use fewer continual\.tasks / plain FL",
        str(caught.value),
    ), str(caught.value)


def test_750_clients_on_1000_scenes_are_refused_with_a_count_that_works_in_a_moment():
    circle = np.random.default_rng(5).random(1000) < 0.5
    table = make_table(circle)
    start = time.perf_counter()
    with pytest.raises(ConfigError) as caught:
        make_split(table, DataConfig(clients=750), BOTH)
    seconds = time.perf_counter() - start
    assert seconds < 3.0  # the search is cut at 1.5 s; an IID one takes milliseconds
    most = int(re.search(r"; data\.clients=(\d+) is the most", str(caught.value)).group(1))
    split = make_split(table, DataConfig(clients=most), BOTH)
    assert task_clients(split) == {"circle": most, "arrow": most}
    with pytest.raises(ConfigError, match=f"^data.clients={most + 1}: "):
        make_split(table, DataConfig(clients=most + 1), BOTH)


# --- make_split --------------------------------------------------------------------------


def music_csv(tmp_path: Path) -> Path:
    """30 scenes (stamps 300..329), 3 ratings each; music (every descriptor 1) in 12."""
    rows = [HEADER]
    for k in range(30):
        music = k % 5 in (0, 3)
        for r in range(3):
            labels = [1 + (k + r + j) % 5 for j in range(8)]
            rows.append(rating_row(300 + k, k % 3 == 0, labels, 1.0 if music else 0.0))
    return write_rows(tmp_path / "all_data.csv", rows)


def test_make_split_with_custom_tasks_on_another_column(tmp_path):
    table = read_ratings(music_csv(tmp_path))
    assert len(table) == 30
    music = table.column(MUSIC) == 1.0
    assert music.sum() == 12
    tasks = (TaskSpec("quiet", MUSIC, 0.0), TaskSpec("music", MUSIC, 1.0))
    split = make_split(table, DataConfig(tasks=tasks, clients=3, seed=2))

    assert_partition([split.train, split.test], np.arange(30))
    # Stratified by task: 18/4 -> 5 quiet (4.5 rounds up) and 12/4 = 3 music scenes in test.
    assert list(split.test_tasks) == ["quiet", "music"]
    assert len(split.test_tasks["quiet"]) == 5 and len(split.test_tasks["music"]) == 3
    assert_partition(split.test_tasks.values(), split.test)
    assert not music[split.test_tasks["quiet"]].any()
    assert music[split.test_tasks["music"]].all()

    assert [c.client for c in split.clients] == [0, 1, 2]
    assert_partition([c.train for c in split.clients], split.train)
    for c in split.clients:
        assert list(c.tasks) == ["quiet", "music"]
        assert_partition(c.tasks.values(), c.train)
        assert not music[c.tasks["quiet"]].any()
        assert music[c.tasks["music"]].all()


def test_make_split_tasks_cover_only_task_scenes(tmp_path):
    table = read_ratings(music_csv(tmp_path))
    music = table.column(MUSIC) == 1.0
    split = make_split(table, DataConfig(tasks=(TaskSpec("music", MUSIC, 1.0),), clients=2))
    # Scenes in no task are still split (as their own group) but no client task holds them.
    assert_partition([split.train, split.test], np.arange(30))
    assert np.array_equal(split.test_tasks["music"], split.test[music[split.test]])
    assert len(split.test_tasks["music"]) == 3
    for c in split.clients:
        assert np.array_equal(c.tasks["music"], c.train[music[c.train]])


@pytest.mark.parametrize("partition", ["iid", "dirichlet"])
def test_make_split_test_set_is_shared_and_disjoint_from_clients(partition):
    circle = np.random.default_rng(0).random(64) < 0.4
    table = make_table(circle)
    splits = {
        n: make_split(
            table, DataConfig(clients=n, seed=11, partition=partition, dirichlet_alpha=100.0)
        )
        for n in (1, 2, 3, 5)
    }
    reference = splits[1]
    n_circle = int(circle.sum())
    assert len(reference.test) == half_up(n_circle / 4) + half_up((64 - n_circle) / 4)
    for n, split in splits.items():
        assert np.array_equal(split.test, reference.test)
        assert np.array_equal(split.train, reference.train)
        for name in ("circle", "arrow"):
            assert np.array_equal(split.test_tasks[name], reference.test_tasks[name])
        assert len(split.clients) == n
        assert_partition([c.train for c in split.clients], split.train)
        for c in split.clients:
            assert not np.isin(c.train, split.test).any()
            assert_partition(c.tasks.values(), c.train)
            assert circle[c.tasks["circle"]].all() and not circle[c.tasks["arrow"]].any()


def test_make_split_is_seeded():
    table = make_table(np.arange(40) % 3 == 0)
    a = make_split(table, DataConfig(clients=2, seed=1))
    b = make_split(table, DataConfig(clients=2, seed=1))
    c = make_split(table, DataConfig(clients=2, seed=2))
    assert np.array_equal(a.test, b.test)
    assert all(np.array_equal(x.train, y.train) for x, y in zip(a.clients, b.clients, strict=True))
    assert not np.array_equal(a.test, c.test)


def test_make_split_label_quartile_partition_key():
    table = make_table(np.arange(48) % 2 == 0)
    config = DataConfig(
        clients=3, partition="dirichlet", partition_key="label", dirichlet_alpha=1e6
    )
    split = make_split(table, config)
    # The task still drives the train/test split; the label quartile only the shards.
    assert len(split.test) == 12
    assert_partition([c.train for c in split.clients], split.train)
    # alpha ~ inf: each client gets a third (+-1 for rounding) of every label quartile.
    mean_label = table.targets.mean(axis=1)
    quartile = np.searchsorted(np.quantile(mean_label, [0.25, 0.5, 0.75]), mean_label)
    assert len(np.unique(quartile[split.train])) > 1
    for q in np.unique(quartile[split.train]):
        n_q = np.sum(quartile[split.train] == q)
        for c in split.clients:
            assert abs(np.sum(quartile[c.train] == q) - n_q / 3) <= 1


def test_task_on_a_non_binary_descriptor_value(tmp_path):
    rows = [HEADER]
    for k in range(8):
        for _ in range(3):  # every rating row of a scene carries the same descriptors
            rows.append(rating_row(300 + k, k % 2 == 0, [3] * 8, 0.7 if k < 4 else 0.2))
    table = read_ratings(write_rows(tmp_path / "all_data.csv", rows))
    tasks = (
        TaskSpec("crowded", "Number of people", 0.7),
        TaskSpec("sparse", "Number of people", 0.2),
    )
    assert np.array_equal(task_members(table, tasks), [0, 0, 0, 0, 1, 1, 1, 1])


@pytest.mark.slow
def test_a_schedule_some_client_cannot_train_is_refused_before_any_image_is_decoded(
    tmp_path, synth_dir, cache_dir, capsys, monkeypatch
):
    """FCL trains every client on each scheduled task in turn: 20 clients on the 36
    training scenes leave some without one. The split is refused in one line from
    all_data.csv - no image decoded, no MLflow run - with how many clients lack each task
    and the most clients that give every client both (they do; one more does not).
    A bad input of issue 40."""

    def never(*args, **kwargs):
        raise AssertionError("images decoded before the split was checked")

    monkeypatch.setattr(dataset_module, "load_image_store", never)
    monkeypatch.setattr(images_module, "decode", never)
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    argv = ["run", str(FAST), f"data.path={synth_dir}", f"data.cache_dir={cache_dir}"]
    assert main([*argv, "--tracking-uri", store, "method=FedAvg-EWC", "data.clients=20"]) == 1
    err = capsys.readouterr().err.strip()

    # What it must say, from plain splits (which allow a client without a task).
    table = read_ratings(synth_dir)
    both = ("circle", "arrow")

    def held(clients: int) -> dict[str, int]:
        return task_clients(make_split(table, DataConfig(clients=clients)))

    lacking = sorted(((20 - k, t) for t, k in held(20).items()), key=lambda kt: -kt[0])
    assert all(k > 0 for k, _ in lacking)
    most = max(k for k in range(1, 20) if held(k) == {"circle": k, "arrow": k})
    assert 1 < most < 19
    assert err == (
        f"fedlgr: error: data.clients=20: {lacking[0][0]} clients hold no training scenes of "
        f"task {lacking[0][1]!r} and {lacking[1][0]} none of {lacking[1][1]!r} (continual.tasks "
        "needs every client to hold each task it trains); "
        f"data.clients={most} is the most that give every client scenes of every task with "
        "data.seed=0, or use fewer continual.tasks / plain FL"
    )
    split = make_split(table, DataConfig(clients=most), both)
    assert all(len(c.tasks[t]) for c in split.clients for t in both)
    with pytest.raises(ConfigError, match=f"^data.clients={most + 1}: "):
        make_split(table, DataConfig(clients=most + 1), both)
    assert not cache_dir.exists()
    client = mlflow.MlflowClient(store)
    assert not client.search_runs([e.experiment_id for e in client.search_experiments()])
