"""Fast dev runs of every method, tracked in a real MLflow store, and the orchestrator."""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys

import mlflow
import pytest
import torch

from fedlgr.core.client.side import ClientSide
from fedlgr.core.messages import EvaluateIns, RoundPlan, TrainIns, nbytes
from fedlgr.core.methods import STRATEGIES
from fedlgr.shell.cli import main
from fedlgr.shell.config import METHODS, load_config
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.splits import make_split
from fedlgr.shell.run.experiment import run_experiment
from tests.support.processes import only_run, run_args
from tests.support.runs import FAST, fast_config, orchestrator, read_run, results_csv

ACTIONS = ("vacuum", "conversation")


# After every edit: each scope, a control variate and a statistic of the uploads; every
# method in the slow tier.
FAST_FL = ("FedAvg", "FedRootAvg", "FedRootSCAFFOLD", "FedMedian")


@pytest.mark.parametrize(
    "method", [m if m in FAST_FL else pytest.param(m, marks=pytest.mark.slow) for m in METHODS]
)
def test_fast_dev_run_trains_evaluates_and_logs(method, synth_dir, cache_dir, store, capsys):
    result = run_experiment(fast_config(synth_dir, cache_dir, store, f"method={method}"))
    client, run, artifacts = read_run(store, result.run_id)

    assert run.info.status == "FINISHED" and run.info.run_name == f"{method}-2c-noaug-image"
    tags = run.data.tags
    scope = "root" if method.startswith("FedRoot") else "full"
    strategy = METHODS[method][0]  # the registry's (fedlgr.core.methods): e.g. FedRootAvgM -> avgm
    assert method.endswith(STRATEGIES[strategy].suffix)
    assert (tags["method"], tags["scope"], tags["strategy"]) == (method, scope, strategy)
    assert (tags["dataset"], tags["clients"], tags["augmentation"]) == ("synthetic", "2", "false")
    params = run.data.params
    assert params["method"] == method and params["federated.scope"] == scope
    assert params["data.clients"] == "2" and params["train.max_batches"] == "2"

    metrics = run.data.metrics
    expected = [
        "test/loss",
        "test/rmse",
        "test/pcc",
        "train/loss",
        "cost/cpu_s",
        "cost/wall_s",
        "cost/bytes_up",
        "cost/bytes_down",
        "round/seconds",
    ]
    for key in expected:
        assert key in metrics, key
        assert math.isfinite(metrics[key]), key
    # Per-action and per-client figures are in results.csv, not in MLflow by default.
    detail = [f"test/{m}/{a}" for m in ("mse", "rmse", "pcc") for a in ACTIONS]
    detail += [
        f"{f}/client{c}/{k}" for c in (0, 1) for f, k in (("test", "rmse"), ("cost", "cpu_s"))
    ]
    assert not [key for key in detail if key in metrics]
    assert "cost/gpu_util" not in metrics  # no NVIDIA GPU: absent, not an error
    assert [m.step for m in client.get_metric_history(result.run_id, "test/rmse")] == [1]
    assert metrics["cost/bytes_up"] > 0 and metrics["cost/cpu_s"] > 0
    # Run-level costs for Tables III/IV: one round here, so the mean over rounds is that round.
    assert metrics["mean/cost/cpu_s"] == pytest.approx(metrics["cost/cpu_s"])
    assert metrics["mean/cost/bytes_up"] == pytest.approx(metrics["cost/bytes_up"])
    assert "mean/cost/gpu_util" not in metrics
    assert (tags["benchmark"], tags["continual"]) == ("FL", "none")

    assert {"config.yaml", "results.csv", "curves.png"} <= artifacts
    rows = results_csv(client, result.run_id)
    assert [(r["round"], r["client"]) for r in rows] == [("1", "0"), ("1", "1")]
    mean_rmse = sum(float(r["test_rmse"]) for r in rows) / len(rows)
    assert metrics["test/rmse"] == pytest.approx(mean_rmse)
    with open(client.download_artifacts(result.run_id, "config.yaml")) as f:
        config_text = f.read()
    assert f"method: {method}" in config_text
    # One name everywhere: the console's summary is the run's MLflow description.
    out = capsys.readouterr().out
    heading = f"{method}-2c-noaug-image after 1 rounds"
    assert heading in out
    note = tags["mlflow.note.content"]
    assert note.startswith(f"**{heading}") and result.summary() in note
    # ... under a table of the headline scores and costs, every headline score's column
    assert "| test/rmse | test/pcc | test/ccc | mean/cost/cpu_s | mean/cost/bytes_up |" in note
    assert "tracking.run_name" not in params


@pytest.mark.parametrize("method", ["FedAvg", "FedRootAvg"])
def test_features_modality_needs_only_the_csv(method, synth_dir, tmp_path, cache_dir, store):
    folder = tmp_path / "csv-only"
    folder.mkdir()
    shutil.copy(synth_dir / "all_data.csv", folder)
    config = fast_config(folder, cache_dir, store, f"method={method}", "data.modality=features")
    assert config.root_kind == "mlp"
    result = run_experiment(config)
    _, run, artifacts = read_run(store, result.run_id)
    assert run.info.status == "FINISHED" and run.data.tags["modality"] == "features"
    assert math.isfinite(run.data.metrics["test/pcc"]) and "results.csv" in artifacts
    assert "fedlgr.task_clients" not in run.data.tags  # both clients hold both tasks


def test_plain_fl_runs_clients_of_one_scene_and_says_how_many_hold_each_task(
    synth_dir, cache_dir, store, capsys
):
    """36 clients on the 36 training scenes: one scene each, so every client holds one task
    only (client 0 too, whose single scene once broke the warm-up step). Plain FL trains a
    client on all its scenes at once, so the run goes through; its header and its tag
    ``fedlgr.task_clients`` say how many clients hold each task."""
    config = fast_config(synth_dir, cache_dir, store, "data.modality=features", "data.clients=36")
    split = make_split(load_scenes(config.data).table, config.data)
    assert [len(c.train) for c in split.clients] == [1] * 36
    held = {t: sum(len(c.tasks[t]) > 0 for c in split.clients) for t in ("circle", "arrow")}
    assert held["circle"] + held["arrow"] == 36 and min(held.values()) > 0

    result = run_experiment(config)
    client, run, _ = read_run(store, result.run_id)
    assert run.info.status == "FINISHED"
    tag = f"circle:{held['circle']}/36, arrow:{held['arrow']}/36"
    assert run.data.tags["fedlgr.task_clients"] == tag
    lines = capsys.readouterr().out.splitlines()
    header = next(
        i for i, line in enumerate(lines) if line.startswith("FedAvg-36c-noaug-features:")
    )
    assert lines[header + 1] == (
        f"clients with training scenes of each task: circle {held['circle']} of 36, "
        f"arrow {held['arrow']} of 36"
    )
    assert sorted(int(r["client"]) for r in results_csv(client, result.run_id)) == list(range(36))


def test_root_scope_keeps_each_top_and_uploads_the_root(synth_dir, cache_dir):
    config = load_config(
        FAST,
        [
            f"data.path={synth_dir}",
            f"data.cache_dir={cache_dir}",
            "method=FedRootAvg",
            "tracking.enabled=false",
        ],
    )
    orch = orchestrator(config)
    trained = orch.client_side.train(TrainIns(RoundPlan(1)))
    tops = [{k: v.clone() for k, v in c.model.top.state_dict().items()} for c in orch.clients]
    roots = [{k: v.clone() for k, v in c.model.root.state_dict().items()} for c in orch.clients]
    assert not torch.equal(tops[0]["net.1.weight"], tops[1]["net.1.weight"])  # they trained apart
    orch.aggregate(trained)
    orch.client_side.evaluate(EvaluateIns(RoundPlan(1), orch.server.global_weights))
    for client, top in zip(orch.clients, tops, strict=True):
        for key, value in client.model.top.state_dict().items():
            assert torch.equal(value, top[key]), key  # bit-identical: the top never left
    root_float = {
        k: v for k, v in orch.clients[0].model.root.state_dict().items() if v.is_floating_point()
    }
    for client, upload in zip(orch.clients, trained, strict=True):
        assert nbytes(upload.weights) == nbytes(root_float)  # uploaded: the root's size
        w = client.n_samples / sum(c.n_samples for c in orch.clients)
        mean = roots[0]["features.0.0.weight"] * w + roots[1]["features.0.0.weight"] * (1 - w)
        assert torch.allclose(
            client.model.root.state_dict()["features.0.0.weight"], mean, atol=1e-6
        )


def test_a_failing_run_is_marked_failed_and_keeps_what_was_logged(
    synth_dir, cache_dir, store, monkeypatch
):
    real = ClientSide.evaluate
    calls = []

    def fail_in_round_two(self, ins):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("disk on fire")
        return real(self, ins)

    monkeypatch.setattr(ClientSide, "evaluate", fail_in_round_two)
    config = fast_config(
        synth_dir, cache_dir, store, "federated.rounds=3", "tracking.run_name=doomed"
    )
    with pytest.raises(RuntimeError, match="disk on fire"):
        run_experiment(config)
    runs = mlflow.MlflowClient(store).search_runs(
        [mlflow.MlflowClient(store).get_experiment_by_name("fedlgr-debug").experiment_id],
        "attributes.run_name = 'doomed'",
    )
    (run,) = runs
    client, run, artifacts = read_run(store, run.info.run_id)
    assert run.info.status == "FAILED"
    assert [m.step for m in client.get_metric_history(run.info.run_id, "test/rmse")] == [1]
    assert "results.csv" in artifacts and {
        r["round"] for r in results_csv(client, run.info.run_id)
    } == {"1"}


def _cli_run(args, cwd):
    done = subprocess.run(
        [sys.executable, "-m", "fedlgr", "run", *args],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=cwd,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


# FedMedian: a statistic of every upload, which the processes gather instead of summing;
# FedRootProx under client-level DP with adaptive clipping: the clipped sums and the sum of
# the centred "within the clip norm" bits reduced, then the same seeded noise in every
# process (the clip norm it moves, privacy/clip, compared)
TWO_PROCESSES = {
    "FedRootProx": [
        "federated.dp.clip=1",
        "federated.dp.noise_multiplier=0.05",
        "federated.dp.delta=0.1",
        "federated.dp.clipping=adaptive",
    ],
    "FedMedian": [],
}


@pytest.mark.slow
@pytest.mark.parametrize("method", list(TWO_PROCESSES))
def test_two_processes_give_the_same_numbers_as_one(method, synth_dir, cache_dir, tmp_path):
    """Fabric DDP on CPU (gloo), clients sharded over 2 processes, vs one process."""
    store = f"sqlite:///{tmp_path}/mlflow.db"
    common = [
        str(FAST),
        f"data.path={synth_dir}",
        f"data.cache_dir={cache_dir}",
        "federated.rounds=2",
        f"method={method}",
        *TWO_PROCESSES[method],
        "runtime.accelerator=cpu",
        "runtime.threads=1",
        "tracking.detail_metrics=true",  # every client's scores compared
    ]
    _cli_run([*common, "tracking.run_name=one", f"--tracking-uri={store}"], tmp_path)
    out = _cli_run(
        [*common, "tracking.run_name=two", "runtime.devices=2", f"--tracking-uri={store}"], tmp_path
    )
    assert "2 processes" in out
    client = mlflow.MlflowClient(store)
    experiment = client.get_experiment_by_name("fedlgr-debug").experiment_id
    runs = {r.info.run_name: r for r in client.search_runs([experiment])}
    one, two = runs["one"], runs["two"]
    assert two.data.params["runtime.devices"] == "2"
    keys = [k for k in one.data.metrics if k.startswith(("test/", "privacy/"))]
    assert len(keys) > 20
    for key in keys:
        assert two.data.metrics[key] == pytest.approx(one.data.metrics[key], abs=1e-5), key
    rows = [results_csv(client, r.info.run_id) for r in (one, two)]
    assert [(r["round"], r["client"]) for r in rows[1]] == [
        ("1", "0"),
        ("1", "1"),
        ("2", "0"),
        ("2", "1"),
    ]
    for a, b in zip(*rows, strict=True):
        assert float(a["train_loss"]) == pytest.approx(float(b["train_loss"]), abs=1e-5)
        assert a["bytes_up"] == b["bytes_up"] and a["bytes_down"] == b["bytes_down"]


def test_fedroot_clients_share_one_pass_of_the_root_over_the_test_set(synth_dir, cache_dir):
    from fedlgr.core.evaluation import predict

    config = fast_config(
        synth_dir,
        cache_dir,
        "sqlite://",
        "method=FedRootAvg",
        "data.clients=3",
        "train.eval_batch_size=5",
        "tracking.enabled=false",
    )
    orch = orchestrator(config)
    orch.run_round(RoundPlan(1))
    side, received = orch.client_side, orch.server.global_weights
    assert side.root_keys and all(side.holds_root(c.index) for c in side.clients)
    passes = [0] * 3
    for k, client in enumerate(side.clients):
        client.model.root.register_forward_hook(
            lambda *_, k=k: passes.__setitem__(k, passes[k] + 1)
        )
    shared = side.predictions(received, [0, 1, 2])
    batches = -(-len(side.test_inputs) // 5)
    assert passes == [batches, 0, 0]  # one root pass over the test set for three clients
    for client in side.clients:  # bit for bit
        assert torch.equal(shared[client.index], predict(client.model, side.test_inputs, 5))
    assert not torch.equal(shared[0], shared[1])  # each with its own top
    with torch.no_grad():  # a client whose root is not the one received is scored alone
        side.clients[2].model.root.features[0][0].weight.add_(1.0)
    passes[:] = [0, 0, 0]
    side.predictions(received, [0, 1, 2])
    assert passes == [batches, batches, batches]


def test_the_test_images_stay_uint8_and_are_normalised_a_batch_at_a_time_with_the_same_numbers(
    synth_dir, cache_dir
):
    from fedlgr.core.data.augment import normalize
    from fedlgr.core.evaluation import predict

    config = fast_config(
        synth_dir, cache_dir, "sqlite://", "data.clients=2", "tracking.enabled=false"
    )
    orch = orchestrator(config)
    inputs = orch.client_side.test_inputs
    assert inputs.raw.dtype == torch.uint8 and inputs.images
    whole = normalize(inputs.raw)  # every scene at once, as before
    assert inputs.raw.nbytes * 4 == whole.nbytes
    for start, stop in [(0, 3), (3, 7), (len(inputs) - 2, len(inputs))]:
        assert torch.equal(inputs.batch(start, stop), whole[start:stop])  # bit for bit
    model = orch.client_side.clients[0].model
    if inputs.channels_last:
        whole = whole.contiguous(memory_format=torch.channels_last)
        assert inputs.batch(0, 3).is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(predict(model, inputs, 4), predict(model, whole, 4))


@pytest.mark.slow
def test_the_fast_config_shows_learning_in_its_default_run(tmp_path):
    """conf/debug/fast.yaml is the smoke test a user runs first: as shipped (no override
    but the data), it must learn something measurable, not print PCC 0.000."""
    from fedlgr.shell.config import CONF_DIR, load_config
    from fedlgr.shell.data.synth import synthesize
    from fedlgr.shell.run.experiment import run_experiment

    synthesize(tmp_path / "synth", scenes=400, seed=0, size=32)
    config = load_config(
        CONF_DIR / "debug" / "fast.yaml",
        [f"data.path={tmp_path / 'synth'}", f"tracking.uri=sqlite:///{tmp_path}/mlflow.db"],
    )
    result = run_experiment(config)
    first, last = result.rounds[0], result.rounds[-1]
    assert last.mean("test_pcc") > 0.1
    assert last.mean("test_rmse") < first.mean("test_rmse") or first.mean("test_pcc") > 0.1


def test_training_gflops_count_one_batch_and_scale_it_the_same_for_fedavg_and_fedroot(
    synth_dir, cache_dir
):
    """``cost/gflops``: fedlgr's flop counter (torch's FlopCounterMode with grouped
    convolutions' backward counted right) on the round's first batch (forward and backward),
    per sample, x the samples the round trained on - the same work for a FedAvg and a
    FedRootAvg client, which the CPU seconds of a shared machine blur."""
    from fedlgr.core.meters.flops import flop_counter
    from fedlgr.core.scope import initial_scholar

    figures = {}
    for method in ("FedAvg", "FedRootAvg"):
        config = fast_config(synth_dir, cache_dir, "sqlite://", f"method={method}")
        orch = orchestrator(config)
        figures[method] = [t.figures for t in orch.client_side.train(TrainIns(RoundPlan(1)))]
    # the count of one step, by hand: the initial model on a batch of 4 images
    model = initial_scholar(config).train()
    x = torch.rand(4, 3, config.data.image_size, config.data.image_size)
    with flop_counter() as counter:
        torch.nn.functional.mse_loss(model(x), torch.zeros(4, 8)).backward()
    per_sample = counter.get_total_flops() / 4
    for fedavg, fedroot in zip(figures["FedAvg"], figures["FedRootAvg"], strict=True):
        assert fedavg["cost/gflops"] == fedroot["cost/gflops"] > 0  # the same work
        assert fedavg["cost/gflops"] == pytest.approx(per_sample * fedavg["train/samples"] / 1e9)


def test_partial_participation_trains_the_chosen_clients_and_scores_every_client(
    synth_dir, cache_dir
):
    """``federated.fraction=0.5`` of 2 clients: one trains a round, drawn from the seed
    (seed 0: client 1, then 0, then 1); the other keeps its state - FedRoot: its top does
    not move - downloads the new root and is scored; the log names the participants."""
    from fedlgr.core.strategies.base import participants

    config = fast_config(
        synth_dir, cache_dir, "sqlite://", "method=FedRootAvg", "federated.fraction=0.5"
    )
    orch = orchestrator(config)
    for round_ in (1, 2, 3):
        chosen = participants(round_, 2, 0.5, config.seed)
        (other,) = {0, 1} - set(chosen)
        top = {k: v.clone() for k, v in orch.clients[other].model.top.state_dict().items()}
        log = orch.run_round(RoundPlan(round_))
        assert log.participants == tuple(chosen) and len(chosen) == 1
        assert log.metrics()["round/participants"] == 1.0
        trained = [c for c in (0, 1) if not math.isnan(log.column("train/loss")[c])]
        assert trained == chosen
        assert math.isnan(log.column("cost/bytes_up")[other])  # it sent nothing
        assert log.column("cost/bytes_down")[other] > 0  # it took the new root to score
        assert not any(math.isnan(v) for v in log.column("test/rmse"))  # both scored
        for key, value in orch.clients[other].model.top.state_dict().items():
            assert torch.equal(value, top[key]), key  # kept, bit for bit
    assert [participants(r, 2, 0.5, 0) for r in (1, 2, 3)] == [[1], [0], [1]]


def test_the_result_says_what_recording_each_round_cost(synth_dir, cache_dir, store):
    """Issue 40: the seconds of each round's MLflow logging and checkpoint, and of the
    end's results.csv, are on the result (for ``bench/scale.py``), one entry per round; a
    round with no checkpoint due (every 2 rounds, and after the last) spent none."""
    config = fast_config(synth_dir, cache_dir, store, "federated.rounds=3", "tracking.checkpoint=2")
    result = run_experiment(config)
    assert len(result.tracking_seconds) == len(result.rounds) == 3
    assert all(s > 0 for s in result.tracking_seconds)
    assert len(result.checkpoint_seconds) == 3
    assert result.checkpoint_seconds[0] == 0.0
    assert all(s > 0 for s in result.checkpoint_seconds[1:])
    assert result.results_seconds > 0
    client, _, _ = read_run(store, result.run_id)
    logged = client.get_run(result.run_id).data.metrics
    assert not [k for k in logged if "tracking" in k or "checkpoint" in k]  # not logged


@pytest.mark.parametrize("variant", ["adam", "yogi", "adagrad"])
@pytest.mark.parametrize("method", ["FedOpt", "FedRootOpt"])
def test_each_fedopt_variant_runs_in_both_scopes_on_the_shared_parameters(
    method, variant, synth_dir, cache_dir
):
    """Reddi et al.'s three server optimisers (``federated.opt.variant``) under both scopes:
    two rounds train, the moments are kept for the shared parameters only (the root's under
    FedRoot; no BatchNorm running statistics), and the second moment starts at tau^2 and
    stays positive (FedYogi's may shrink, never below 0 from tau^2 with its sign rule)."""
    config = fast_config(
        synth_dir, cache_dir, "sqlite://", f"method={method}", f"federated.opt.variant={variant}"
    )
    orch = orchestrator(config)
    first = {k: v.clone() for k, v in orch.server.global_weights.items()}
    for r in (1, 2):
        orch.run_round(RoundPlan(r))
    strategy = orch.server.strategy
    assert set(strategy.v) == strategy.trainable and strategy.trainable
    assert all(k.startswith("root.") for k in strategy.v) == (method == "FedRootOpt")
    assert all(bool((v > 0).all()) for v in strategy.v.values())
    moved = [
        k for k in strategy.trainable if not torch.equal(first[k], orch.server.global_weights[k])
    ]
    assert moved  # the server step moved the global parameters


# (A NaN learning rate is refused with the config now: tests/test_config.py.)
@pytest.mark.parametrize(
    "rates",
    [
        ["train.lr_root=1e30", "train.lr_top=1e30"],
        # the server's step: finite in round 1, then every client's loss in round 2
        ["method=FedAvgM", "federated.avgm.lr=1e30"],
    ],
    ids=["huge", "huge-server-lr"],
)
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_a_non_finite_training_loss_is_one_error_line_and_a_failed_run(
    rates, synth_dir, cache_dir, tmp_path, monkeypatch, capfd
):
    store = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.chdir(tmp_path)
    code = main(["run", *run_args(synth_dir, cache_dir, store, "federated.rounds=2", *rates)])
    err = capfd.readouterr().err
    assert code == 1, err
    assert "Traceback" not in err
    errors = [line for line in err.splitlines() if line.startswith("fedlgr: error:")]
    assert len(errors) == 1, err
    assert re.fullmatch(
        r"fedlgr: error: round [12], client \d+: the training loss is (nan|inf|-inf) "
        r"\(not a finite number\); lower the learning rates .*",
        errors[0],
    ), errors[0]
    assert "federated.avgm.lr" in errors[0]  # the server's, where one steps
    _, run = only_run(store)
    assert run.info.status == "FAILED"
