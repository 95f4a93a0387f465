"""The LEAP-HRI'24 benchmark's presets (conf/experiment/leap_hri24/, docs/leap_hri24.md):
its model, optimiser, augmentation and scores, run for a round on the synthetic
descriptors. (tests/test_config.py loads and builds every preset with the others.)"""

from __future__ import annotations

import math

import pytest
import torch

from fedlgr.core.meters.scores import batch_scores, compat_order, regression_scores
from fedlgr.core.models.scholar import build_scholar
from fedlgr.core.schedule import schedule
from fedlgr.shell.config import CONF_DIR, load_config
from fedlgr.shell.data.synth import synthesize
from fedlgr.shell.run.experiment import run_experiment
from tests.support.runs import orchestrator, read_run

PRESETS = CONF_DIR / "experiment" / "leap_hri24"
TASKS = ("circle", "arrow")


@pytest.fixture(scope="module")
def descriptors(tmp_path_factory):
    """160 synthetic scenes (tiny images: only all_data.csv is read): 40 test scenes, so
    that the test set after Task 2 is two batches of 16 and 8 rows dropped."""
    out = tmp_path_factory.mktemp("leap") / "manners-synth"
    synthesize(out, scenes=160, seed=7, size=16)
    return out


def preset(name: str, synth_dir, store, *overrides):
    return load_config(
        PRESETS / f"{name}.yaml",
        [f"data.path={synth_dir}", f"tracking.uri={store}", *overrides],
    )


@pytest.mark.parametrize("name", ["fl_clients2_noaug", "fcl_clients10_aug"])
def test_the_presets_are_the_authors_settings(name, synth_dir, store):
    config = preset(name, synth_dir, store)
    model = build_scholar(config)
    linear = [m for m in model.modules() if isinstance(m, torch.nn.Linear)]
    norms = [m for m in model.modules() if isinstance(m, torch.nn.BatchNorm1d)]
    inputs = 27 if name.startswith("fcl") else 29  # FCL: the descriptors; FL: + the 2 flags
    shapes = [(m.in_features, m.out_features) for m in linear]
    assert shapes == [(inputs, 16), (16, 16), (16, 8)] and len(norms) == 2
    assert not any(isinstance(m, torch.nn.ReLU) for m in model.modules())
    optimizer = model.configure_optimizers()
    decay = 0.01 if name.startswith("fcl") else 0.0
    assert {(g["lr"], g["weight_decay"]) for g in optimizer.param_groups} == {(0.01, decay)}
    assert type(optimizer) is torch.optim.Adam and config.train.reset_optimizer
    assert (config.train.epochs, config.train.batch_size, config.total_rounds) == (10, 16, 10)


def test_an_fl_preset_trains_a_round_on_the_scenes_and_their_noisy_copies(descriptors, store):
    """Their FL notebooks' augmentation: each scene and 8 noisy copies (9 rows); their
    scores are the whole test set's (no batches), the server's of the global model."""
    overrides = ["federated.rounds=1", "train.epochs=1"]
    config = preset("fl_clients2_aug", descriptors, store, *overrides)
    orch = orchestrator(config)
    side = orch.client_side
    for client in side.clients:
        batches = client.batches
        n = len(batches.positions)
        assert batches.samples_per_epoch == 9 * n
        assert not batches.noise[:n].any() and batches.noise[n:, :27].all()
    log = orch.run_round(schedule(config)[0])
    model = build_scholar(config).eval()
    model.load_state_dict(orch.server.global_weights)
    with torch.no_grad():
        pred = model(side.test_inputs.whole())
    expected = regression_scores(pred, side.test_targets)
    for name in ("rmse", "pcc"):
        # float32 outputs of the same model, summed in another order: 1e-5
        assert log.metrics()[f"test/{name}"] == pytest.approx(expected.mean(name), abs=1e-5)
        assert log.server[f"server/test/{name}"] == pytest.approx(expected.mean(name), abs=1e-5)
    orch.close()


def test_an_fcl_preset_trains_on_noisy_copies_and_scores_per_batch(descriptors, store):
    """A round per task: each client trains on 25 noisy copies of its scenes, and every
    score is the authors' per-batch one (train.compat_batch_metrics): the global model's
    outputs cut into batches of 16 in their order (each task's test scenes shuffled, Task 1's
    first), the RMSE of each flattened batch averaged - the clients' and the server's."""
    overrides = ["continual.rounds_per_task=1", "train.epochs=1", "federated.server_eval=on"]
    config = preset("fcl_clients2_aug", descriptors, store, *overrides, "method=FedAvg-NR")
    orch = orchestrator(config)
    side = orch.client_side
    assert len(side.test_targets) == 40 and len(side.test.compat_seen[1]) == 40
    for client in side.clients:
        batches = client.batches
        assert batches.samples_per_epoch == 25 * len(batches.positions)
        assert batches.noise is not None and batches.noise[:, :27].std() > 0
    for plan in schedule(config):
        log = orch.run_round(plan)
        model = build_scholar(config).eval()
        model.load_state_dict(orch.server.global_weights)
        with torch.no_grad():
            pred = model(side.test_inputs.whole())
        rows = torch.cat([compat_order(side.test_rows[t], k) for k, t in enumerate(TASKS)])
        rows = rows if plan.task == 1 else compat_order(side.test_rows["circle"], 0)
        expected = batch_scores(pred[rows], side.test_targets[rows])
        ordered = rows.sort().values  # stamp order: other batches, other figures
        in_stamp_order = batch_scores(pred[ordered], side.test_targets[ordered])
        assert in_stamp_order.mean("rmse") != pytest.approx(expected.mean("rmse"), abs=1e-5)
        metrics = log.metrics()
        for name in ("rmse", "pcc", "loss"):
            # float32 outputs of the same model, summed in another order: 1e-5
            assert metrics[f"test/{name}"] == pytest.approx(expected.mean(name), abs=1e-5)
            assert log.server[f"server/test/{name}"] == pytest.approx(expected.mean(name), abs=1e-5)
    orch.close()


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, overrides",
    [
        ("fl_clients2_noaug", ["federated.rounds=1", "method=FedProx"]),
        ("fcl_clients2_aug", ["continual.rounds_per_task=1", "method=FedAvg-EWC"]),
    ],
)
def test_a_preset_runs_end_to_end(name, overrides, descriptors, store):
    config = preset(name, descriptors, store, "train.epochs=1", *overrides)
    result = run_experiment(config, show_runs=False)
    _, run, _ = read_run(store, result.run_id)
    assert run.info.status == "FINISHED" and run.data.tags["modality"] == "features"
    assert run.data.params["train.weight_decay"] == str(config.train.weight_decay)
    assert math.isfinite(run.data.metrics["test/pcc"])
