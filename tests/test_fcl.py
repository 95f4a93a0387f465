"""Fast dev runs of every Table II method through two tasks, tracked in a real MLflow store."""

from __future__ import annotations

import math

import pytest

from fedlgr.core.messages import nbytes
from fedlgr.core.metrics import SCORES
from fedlgr.core.models.scholar import build_scholar
from fedlgr.shell.config import FCL_METHODS
from fedlgr.shell.run.experiment import run_experiment
from tests.support.runs import fast_config, read_run, results_csv

TABLE2 = [m for m in FCL_METHODS if not m.endswith("-FT")]


def test_table2_has_thirteen_methods():
    assert len(TABLE2) == 13 and "FedLGR" in TABLE2 and "FedRoot-EWCOnline" in TABLE2
    assert "FedAvg-LwF" in TABLE2 and "FedRoot-LwF" in TABLE2


# FedLGR's run (seconds) is in the full suite; test_lgr.py runs it in the fast tier.
# Two methods after every edit (a penalty and a memory, one per scope); all 13 in the slow tier.
FAST_FCL = ("FedAvg-EWC", "FedRoot-NR")


@pytest.mark.parametrize(
    "method", [m if m in FAST_FCL else pytest.param(m, marks=pytest.mark.slow) for m in TABLE2]
)
def test_fcl_fast_dev_run_logs_tasks_and_forgetting(method, synth_dir, cache_dir, store):
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        f"method={method}",
        "continual.rounds_per_task=1",
        "continual.lgr.epochs=2",
    )
    assert config.continual.tasks == ("circle", "arrow") and config.total_rounds == 2
    result = run_experiment(config)
    client, run, artifacts = read_run(store, result.run_id)
    assert run.info.status == "FINISHED" and run.data.tags["method"] == method
    assert run.data.params["continual.tasks"] == "['circle', 'arrow']"

    metrics = run.data.metrics
    keys = [
        f"{p}/{m}"
        for p in (
            "test",
            "task/circle",
            "task/arrow",
            "forgetting/circle",
            "after_task1/test",
            "after_task2/test",
            "after_task2/task/circle",
            "after_task2/forgetting/circle",
        )
        for m in ("loss", "rmse", "pcc")
    ]
    for key in keys:
        assert key in metrics and math.isfinite(metrics[key]), key
    assert "task/client1/circle/rmse" not in metrics  # per client: results.csv, not MLflow
    history = lambda key: [(m.step, m.value) for m in client.get_metric_history(result.run_id, key)]  # noqa: E731
    assert [s for s, _ in history("task/circle/rmse")] == [1, 2]
    assert [s for s, _ in history("forgetting/circle/rmse")] == [2]
    assert [s for s, _ in history("after_task1/test/rmse")] == [1]

    # Forgetting by hand from the per-client CSV: circle's RMSE after arrow minus after circle.
    rows = results_csv(client, result.run_id)
    assert [(r["round"], r["task"]) for r in rows] == [("1", "circle")] * 2 + [("2", "arrow")] * 2
    by_hand = (
        sum(
            float(rows[2 + c]["task_circle_rmse"]) - float(rows[c]["task_circle_rmse"])
            for c in (0, 1)
        )
        / 2
    )
    assert metrics["forgetting/circle/rmse"] == pytest.approx(by_hand, abs=1e-9)
    pcc = (
        sum(
            float(rows[c]["task_circle_pcc"]) - float(rows[2 + c]["task_circle_pcc"])
            for c in (0, 1)
        )
        / 2
    )
    assert metrics["forgetting/circle/pcc"] == pytest.approx(pcc, abs=1e-9)
    # "After Task 1" is on circle's test scenes; "after Task 2" on circle + arrow.
    assert metrics["after_task1/test/rmse"] == pytest.approx(
        sum(float(rows[c]["task_circle_rmse"]) for c in (0, 1)) / 2, abs=1e-9
    )
    assert "results.csv" in artifacts and "curves.png" in artifacts


@pytest.mark.slow
def test_fedlgr_uploads_exactly_the_root_every_round(synth_dir, cache_dir, store):
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        "method=FedLGR",
        "continual.rounds_per_task=2",
        "continual.lgr.epochs=2",
        "tracking.detail_metrics=true",  # per-client metrics in MLflow too
    )
    result = run_experiment(config)
    root = build_scholar(config).root.state_dict()
    root_bytes = nbytes({k: v for k, v in root.items() if v.is_floating_point()})
    client, _, _ = read_run(store, result.run_id)
    for c in (0, 1):
        ups = [
            m.value for m in client.get_metric_history(result.run_id, f"cost/client{c}/bytes_up")
        ]
        assert ups == [root_bytes] * 4


@pytest.mark.slow
def test_end_of_task_work_is_billed_to_the_clients_round(synth_dir, cache_dir, store, monkeypatch):
    """FedLGR's generator training happens at the end of a task: its CPU time must appear in
    that round's cost of the client (a busy loop of 2 CPU s stands in for it here; the
    other rounds of this fast run take well under that, replay included)."""
    import time as clock

    from fedlgr.core.continual.lgr import LatentReplay

    real = LatentReplay.on_task_end

    def busy(self, ctx):
        end = clock.process_time() + 2.0
        while clock.process_time() < end:
            pass
        real(self, ctx)

    monkeypatch.setattr(LatentReplay, "on_task_end", busy)
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        "method=FedLGR",
        "continual.rounds_per_task=2",
        "continual.lgr.epochs=1",
        "runtime.threads=1",  # no OpenMP spin-waiting to inflate the other rounds' CPU time
    )
    result = run_experiment(config)
    cpu = [log.column("cpu_s") for log in result.rounds]  # rounds 2 and 4 end a task
    for c in (0, 1):
        assert cpu[1][c] >= 2.0 and cpu[3][c] >= 2.0, cpu
        assert cpu[0][c] < 2.0 and cpu[2][c] < 2.0, cpu


def test_schedule_steps_mark_task_boundaries():
    from fedlgr.core.schedule import schedule
    from fedlgr.shell.config import load_config

    fl = schedule(load_config(None, ["federated.rounds=3"]))
    assert [(s.round, fl.tasks[s.task], s.first_of_task, s.last_of_task) for s in fl] == [
        (1, "all", True, False),
        (2, "all", False, False),
        (3, "all", False, False),
    ]
    fcl = schedule(load_config(None, ["method=FedRoot-SI", "continual.rounds_per_task=2"]))
    assert [(s.round, fcl.tasks[s.task], s.first_of_task, s.last_of_task) for s in fcl] == [
        (1, "circle", True, False),
        (2, "circle", False, True),
        (3, "arrow", True, False),
        (4, "arrow", False, True),
    ]


@pytest.mark.slow
def test_three_tasks_forget_the_two_before(tmp_path, cache_dir, store):
    """Tasks are data: three tasks by number of animals (0, 1, 2), in that order."""
    from fedlgr.shell.data.synth import synthesize

    synthesize(tmp_path / "d", scenes=90, seed=2, size=16)
    spec = ", ".join(
        f"{{name: {name}, column: Number of animals, value: {value}}}"
        for name, value in (("none", 0), ("one", 0.5), ("two", 1))
    )
    tasks = f"data.tasks=[{spec}]"
    config = fast_config(
        tmp_path / "d",
        cache_dir,
        store,
        tasks,
        "data.clients=1",
        "method=FedRoot-MAS",
        "continual.rounds_per_task=1",
        "data.image_size=16",
    )
    assert config.continual.tasks == ("none", "one", "two")
    result = run_experiment(config)
    # every score on all seen tasks, on each seen task, and the forgetting of each past one
    n = len(SCORES)
    assert [len(a) for a in result.after_tasks] == [n + n, n + 2 * n + n, n + 3 * n + 2 * n]
    after3 = result.after_tasks[2]
    for task in ("none", "one"):
        assert math.isfinite(after3[f"after_task3/forgetting/{task}/rmse"])
    assert "after_task3/forgetting/two/rmse" not in after3


@pytest.mark.slow
@pytest.mark.parametrize("method", ["FedRoot-SI", "FedAvg-NR", "FedLGR"])
def test_a_client_the_strategy_never_chose_in_a_task_still_starts_and_ends_it(
    method, synth_dir, cache_dir, store
):
    """``federated.fraction=0.5`` of 2 clients, one round a task (seed 0: client 1 trains
    the circle round, client 0 the arrow round): the schedule is the same, every client
    ends every task - one that trained in none of its rounds is told of its start first -
    and every client is scored after each."""
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        f"method={method}",
        "federated.fraction=0.5",
        "continual.rounds_per_task=1",
        "continual.lgr.epochs=2",
    )
    result = run_experiment(config)
    assert [log.task for log in result.rounds] == ["circle", "arrow"]
    assert [log.participants for log in result.rounds] == [(1,), (0,)]
    for log in result.rounds:
        assert not any(math.isnan(v) for v in log.column("test/rmse"))
    after = result.after_tasks[1]
    assert math.isfinite(after["after_task2/forgetting/circle/rmse"])
