"""The GPU paths: CUDA-only tests (marker ``gpu``, skipped with a reason without CUDA;
``bench/gpu.py`` runs them on a device), and on any machine the plumbing of the clients'
GPU seconds (``cost/gpu_s``) with a fake timer."""

from __future__ import annotations

import math

import pytest
import torch

from fedlgr.core.meters.costs import Usage, measure
from fedlgr.core.metrics import combine, shared_out
from fedlgr.shell.run.experiment import run_experiment
from tests.support.runs import fast_config, read_run, results_csv

CUDA = torch.cuda.is_available()
NO_CUDA = "needs a CUDA GPU (torch.cuda.is_available() is False here); bench/gpu.py runs it"


def cuda_only(test):
    """Marker ``gpu``, and skipped with :data:`NO_CUDA` where there is no CUDA GPU."""
    return pytest.mark.gpu(pytest.mark.skipif(not CUDA, reason=NO_CUDA)(test))


class FakeTimer:
    """Stands in for the CUDA events: ``seconds`` per measured block."""

    def __init__(self, seconds: float):
        self.seconds, self.started, self.stopped = seconds, 0, 0

    def start(self) -> None:
        self.started += 1

    def stop(self) -> float:
        self.stopped += 1
        return self.seconds


# --------------------------------------------------------------------------- any machine


def test_measure_takes_gpu_seconds_from_its_timer_and_none_without_one():
    timer = FakeTimer(0.25)
    with measure(torch.device("cpu"), timer=timer) as usage:
        pass
    assert (timer.started, timer.stopped, usage.gpu_s) == (1, 1, 0.25)
    with measure(torch.device("cpu")) as usage:
        pass
    assert usage.gpu_s is None  # a CPU device: no CUDA events, absent rather than 0


def test_gpu_seconds_add_up_and_are_shared_by_samples():
    names = ("cpu_s", "wall_s", "gpu_util", "gpu_mem_mb", "gpu_s")

    def costs(figures: dict[str, float]) -> tuple:
        return tuple(figures.get(f"cost/{n}") for n in names)

    both = combine(
        Usage(1.0, 2.0, 50.0, 10.0, 0.5).figures(), Usage(3.0, 2.0, 100.0, 30.0, 1.5).figures()
    )
    assert costs(both) == (4.0, 4.0, 75.0, 30.0, 2.0)
    assert (
        combine(Usage(1.0, 1.0).figures(), Usage(1.0, 1.0, gpu_s=0.5).figures())["cost/gpu_s"]
        == 0.5
    )
    assert "cost/gpu_s" not in combine(Usage(1.0, 1.0).figures(), Usage(1.0, 1.0).figures())
    part = shared_out(Usage(4.0, 2.0, 80.0, 12.0, 2.0).figures(), 0.25)  # a stacked client's
    assert costs(part) == (1.0, 2.0, 80.0, 12.0, 0.5)


def test_a_clients_gpu_seconds_reach_results_csv_and_mlflow(
    synth_dir, cache_dir, store, monkeypatch
):
    """Each client's training is measured with the timer (the fake one here: 0.125 s a
    block): results.csv has gpu_s per client, MLflow the mean ``cost/gpu_s``."""
    from fedlgr.core.meters import costs as resources

    real = resources.measure

    def with_fake_timer(device, per_thread=False, timer=None):
        return real(device, per_thread, FakeTimer(0.125))

    monkeypatch.setattr("fedlgr.core.client.side.measure", with_fake_timer)
    config = fast_config(synth_dir, cache_dir, store, "federated.rounds=2", "data.clients=2")
    result = run_experiment(config)
    client, run, _ = read_run(store, result.run_id)
    rows = results_csv(client, result.run_id)
    assert len(rows) == 4 and all(float(r["gpu_s"]) == 0.125 for r in rows)
    assert run.data.metrics["cost/gpu_s"] == 0.125
    assert result.cost_means()["mean/cost/gpu_s"] == 0.125


def test_the_gpu_tests_are_collected_and_skipped_with_a_reason_without_cuda(pytestconfig):
    if CUDA:
        pytest.skip("a CUDA GPU is here: the gpu tests run")
    for test in (
        test_one_round_on_the_gpu_measures_every_gpu_figure,
        test_mixed_precision_on_the_gpu_trains_with_finite_losses_near_fp32,
        test_threads_and_stacked_clients_on_the_gpu_compute_what_sequential_computes,
    ):
        marks = {m.name: m for m in test.pytestmark}
        assert "gpu" in marks and marks["skipif"].kwargs["reason"] == NO_CUDA


# --------------------------------------------------------------------------- CUDA only


@cuda_only
@pytest.mark.parametrize("concurrency", ["sequential", "threads", "batched"])
def test_one_round_on_the_gpu_measures_every_gpu_figure(concurrency, synth_dir, cache_dir, store):
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        "runtime.accelerator=gpu",
        f"runtime.concurrency={concurrency}",
        "runtime.threads=2",
        "data.clients=2",
        "federated.rounds=1",
    )
    result = run_experiment(config)
    rows = result.rows()
    assert len(rows) == 2
    for row in rows:
        assert math.isfinite(row["train_loss"]) and math.isfinite(row["test_rmse"])
        assert row["gpu_s"] > 0 and row["gpu_mem_mb"] > 0
        assert row["gpu_s"] <= row["wall_s"] + 1e-3  # a span on the stream, within the wall
    assert result.config.runtime.concurrency == concurrency


@cuda_only
@pytest.mark.parametrize("precision", ["16-mixed", "bf16-mixed"])
def test_mixed_precision_on_the_gpu_trains_with_finite_losses_near_fp32(
    precision, synth_dir, cache_dir, store
):
    common = ["runtime.accelerator=gpu", "federated.rounds=2", "data.clients=2"]
    runs = {
        p: run_experiment(fast_config(synth_dir, cache_dir, store, *common, f"train.precision={p}"))
        for p in ("32-true", precision)
    }
    losses = {p: [r["train_loss"] for r in result.rows()] for p, result in runs.items()}
    assert all(math.isfinite(v) for v in losses[precision])
    fp32, mixed = (runs[p].final.mean("test_rmse") for p in ("32-true", precision))
    assert mixed == pytest.approx(fp32, abs=0.05)


@cuda_only
def test_threads_and_stacked_clients_on_the_gpu_compute_what_sequential_computes(
    synth_dir, cache_dir, store
):
    """Each runtime.concurrency gives the sequential scores to float tolerance on a GPU
    (kernels may differ by the stream and the stacking: not bit for bit)."""
    scores = {}
    for mode in ("sequential", "threads", "batched"):
        config = fast_config(
            synth_dir,
            cache_dir,
            store,
            "runtime.accelerator=gpu",
            f"runtime.concurrency={mode}",
            "runtime.threads=2",
            "data.clients=2",
            "federated.rounds=2",
        )
        scores[mode] = [r["test_rmse"] for r in run_experiment(config).rows()]
    for mode in ("threads", "batched"):
        assert scores[mode] == pytest.approx(scores["sequential"], abs=1e-3), mode
