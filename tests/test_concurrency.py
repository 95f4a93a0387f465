"""Clients trained side by side in threads (``runtime.concurrency=threads``) compute what
they compute one after another, for a seed."""

from __future__ import annotations

import gc
import threading

import pytest
import torch

from fedlgr.core.client import pool as concurrency
from fedlgr.core.meters.costs import Usage, share_process_cpu
from fedlgr.errors import FedlgrError
from fedlgr.shell.config import ConfigError
from fedlgr.shell.run.experiment import run_experiment
from tests.support.runs import fast_config, read_run, results_csv

CPU = torch.device("cpu")

# Wall and CPU seconds are measured, not computed: every other column must be equal.
MEASURED = {"cpu_s", "wall_s", "gpu_util", "gpu_mem_mb", "end_cpu_s", "end_wall_s"}

METHODS = {
    "FedAvg": ["federated.rounds=2"],
    "FedRootAvg": ["federated.rounds=2"],
    "FedLGR": ["continual.rounds_per_task=1", "continual.lgr.epochs=2"],
    "FedRoot-NR": ["continual.rounds_per_task=1"],
}


# FedRootAvg in the fast tier; the other methods (seconds each) in the full suite.
@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS)
def test_threads_give_the_results_of_sequential_training(method, synth_dir, cache_dir, store):
    """Sequential with one thread vs 2 threads split over 2 clients (one each): the same
    per-client thread count, so results.csv is identical apart from measured costs."""
    common = [f"method={method}", "data.clients=2", *METHODS[method]]
    runs = {}
    for name, settings in {
        "sequential": ["runtime.threads=1", "runtime.concurrency=sequential"],
        "threads": ["runtime.threads=2", "runtime.concurrency=threads"],
    }.items():
        config = fast_config(
            synth_dir, cache_dir, store, *common, *settings, f"tracking.run_name={name}"
        )
        runs[name] = run_experiment(config)
    client, seq, _ = read_run(store, runs["sequential"].run_id)
    _, thr, _ = read_run(store, runs["threads"].run_id)
    assert thr.data.params["runtime.concurrency"] == "threads"
    assert thr.data.params["runtime.workers"] == "2"
    assert seq.data.params["runtime.concurrency"] == "sequential"

    a, b = (results_csv(client, r.run_id) for r in runs.values())
    assert len(a) == len(b) >= 4 and a[0].keys() == b[0].keys()
    compared = [k for k in a[0] if k not in MEASURED]
    assert {"train_loss", "test_rmse", "test_pcc"} <= set(compared) or len(compared) > 10
    for row_a, row_b in zip(a, b, strict=True):
        assert {k: row_a[k] for k in compared} == {k: row_b[k] for k in compared}
    # Per-client CPU seconds are still per client: both clients report their own share.
    cpu = [float(r["cpu_s"]) for r in b]
    assert all(c > 0 for c in cpu)


def test_auto_picks_threads_on_cpu_with_several_clients_and_threads(synth_dir, cache_dir):
    def resolved(*overrides, clients=2, device="cpu"):
        rt = fast_config(synth_dir, cache_dir, "sqlite://", *overrides).runtime
        chosen = concurrency.Resolved.decide(
            rt.concurrency, rt.workers, rt.threads, torch.device(device), clients
        )
        return chosen.concurrency, chosen.workers

    assert resolved("runtime.threads=2") == ("threads", 2)
    assert resolved("runtime.threads=16", clients=10) == ("threads", 10)
    assert resolved("runtime.threads=1") == ("sequential", 1)  # nothing to split
    assert resolved("runtime.threads=4", clients=1) == ("sequential", 1)
    assert resolved("runtime.threads=4", "runtime.workers=3", clients=10) == ("threads", 3)
    # A GPU: not measured on hardware yet, so not the default there.
    assert resolved("runtime.threads=4", device="cuda") == ("sequential", 1)
    assert resolved("runtime.threads=4", "runtime.concurrency=threads", device="cuda") == (
        "threads",
        2,
    )
    with pytest.raises(ConfigError, match=r"runtime\.concurrency='async'"):
        fast_config(synth_dir, cache_dir, "sqlite://", "runtime.concurrency=async")


def test_the_pool_splits_the_threads_and_keeps_the_order():
    pool = concurrency.ClientPool(2, 4, torch.device("cpu"))
    main = torch.get_num_threads()
    seen = pool.map(
        lambda k: (k, torch.get_num_threads(), threading.current_thread().name), [0, 1, 2]
    )
    assert [k for k, _, _ in seen] == [0, 1, 2]
    assert {n for _, n, _ in seen} == {2}  # 4 threads over 2 workers
    assert all(name.startswith("fedlgr-client") for _, _, name in seen)
    assert torch.get_num_threads() == main

    def fails(k):
        if k == 1:
            raise ValueError("client 1 diverged")
        return k

    with pytest.raises(ValueError, match="client 1 diverged"):
        pool.map(fails, [0, 1, 2])


def test_a_dropped_pool_takes_its_worker_threads_with_it():
    def workers() -> set[threading.Thread]:
        return {t for t in threading.enumerate() if t.name.startswith("fedlgr-client")}

    before = workers()
    pool = concurrency.ClientPool(2, 2, torch.device("cpu"))
    pool.each_worker(lambda: None)  # both threads started
    mine = workers() - before
    assert len(mine) == 2
    del pool
    gc.collect()
    for thread in mine:
        thread.join(timeout=10)
    assert not [t for t in mine if t.is_alive()]  # a sweep's trials do not pile them up


def test_process_cpu_is_shared_in_proportion_to_each_thread():
    usages = [Usage(cpu_s=1.0), Usage(cpu_s=3.0)]
    share_process_cpu(usages, 8.0)
    assert [u.cpu_s for u in usages] == [2.0, 6.0]


@pytest.mark.slow
def test_batched_client_side_trains_what_sequential_training_trains(synth_dir, cache_dir, store):
    """``ClientSide.train`` with runtime.concurrency=batched (CPU here: not yet measured on
    a GPU) against sequential, in float64 (see tests/test_batched.py for why float32
    cannot be compared over many steps on the fast config)."""
    from fedlgr.core.client.side import ClientSide
    from fedlgr.core.messages import RoundPlan, TrainIns
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.data.splits import make_split
    from tests.support.float64 import Float64Batches, assert_close_f64

    class Float64Data(Float64Batches):  # and the rest of SceneBatches (positions, ...)
        def __getattr__(self, name):
            return getattr(self.batches, name)

    trained = {}
    for mode in ("sequential", "batched"):
        config = fast_config(
            synth_dir,
            cache_dir,
            store,
            "method=FedRootAvg",
            "data.clients=3",
            "train.max_batches=null",
            f"runtime.concurrency={mode}",
        )
        scenes = load_scenes(config.data)
        side = ClientSide(config, scenes, make_split(scenes.table, config.data), [0, 1, 2], CPU)
        before = {k: v.clone() for k, v in side.clients[0].model.state_dict().items()}
        for c in side.clients:
            c.model.double()
            c.data = {t: Float64Data(b) for t, b in c.data.items()}
        trained[mode] = side.train(TrainIns(RoundPlan(1, 0, True, True)))
    for seq, bat in zip(trained["sequential"], trained["batched"], strict=True):
        b, s = bat.figures, seq.figures
        assert (bat.client, bat.n_samples, b["train/samples"]) == (
            seq.client,
            seq.n_samples,
            s["train/samples"],
        )
        assert b["train/loss"] == pytest.approx(s["train/loss"], rel=1e-9)
        assert bat.weights.keys() == seq.weights.keys()
        assert all(k.startswith("root.") for k in bat.weights)  # FedRoot: the root alone
        for key in bat.weights:
            assert_close_f64(bat.weights[key], seq.weights[key])
        assert b["cost/cpu_s"] > 0 and b["cost/wall_s"] > 0
    moved = [k for k, v in trained["batched"][0].weights.items() if k in before]
    assert any(
        not torch.allclose(trained["batched"][0].weights[k].float(), before[k].float())
        for k in moved
    )


def test_batched_clients_with_plugins_are_refused_before_the_run(synth_dir, cache_dir, store):
    config = fast_config(
        synth_dir, cache_dir, store, "method=FedProx", "runtime.concurrency=batched"
    )
    with pytest.raises(FedlgrError, match=r"client 0 \(fedprox\).*runtime\.concurrency=threads"):
        run_experiment(config)


def test_an_interrupt_stops_the_other_clients_at_their_next_step():
    """Ctrl-C reaches the main thread only: the clients still training in the pool stop at
    their next step (``stop``) instead of finishing their round before the run can end."""
    pool = concurrency.ClientPool(2, 2, CPU)
    started, steps = threading.Barrier(2), []

    def client(k):
        if k == 0:
            started.wait()
            raise KeyboardInterrupt  # as the main thread would see it
        started.wait()
        for step in range(1000):  # a long round, checking ``stop`` as train_locally does
            if pool.stop.is_set():
                steps.append(step)
                raise RuntimeError("stopped")
            threading.Event().wait(0.01)
        steps.append(1000)

    with pytest.raises(KeyboardInterrupt):
        pool.map(client, [0, 1])
    assert steps and steps[0] < 1000  # client 1 gave up early
    assert not pool.stop.is_set()  # the next round starts clean
