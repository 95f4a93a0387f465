"""Simulated faults (``federated.faults.*``): drop-outs, stragglers and Byzantine clients
(altered uploads, poisoned labels), seeded, on hand numbers and in runs whose rounds count
them and whose results.csv says which client failed how."""

from __future__ import annotations

import math

import mlflow
import pytest
import torch

from fedlgr.core.faults import Faults
from fedlgr.core.messages import TrainRes
from fedlgr.errors import ConfigError
from fedlgr.shell.config import FaultsConfig, load_config
from fedlgr.shell.run.experiment import run_experiment
from tests.support.runs import fast_config, results_csv


def test_byzantine_clients_and_drop_outs_are_drawn_from_the_seed():
    faults = Faults(FaultsConfig(dropout=0.5, byzantine=2), clients=10, seed=0)
    again = Faults(FaultsConfig(dropout=0.5, byzantine=2), clients=10, seed=0)
    other = Faults(FaultsConfig(dropout=0.5, byzantine=2), clients=10, seed=1)
    assert len(faults.byzantine) == 2 and faults.byzantine == again.byzantine
    assert faults.byzantine <= set(range(10))
    rounds = [faults.dropped(r, list(range(10))) for r in range(1, 21)]
    assert rounds == [again.dropped(r, list(range(10))) for r in range(1, 21)]
    assert rounds != [other.dropped(r, list(range(10))) for r in range(1, 21)]
    share = sum(map(len, rounds)) / 200
    assert 0.4 < share < 0.6  # about half of 200 draws
    assert Faults(FaultsConfig(), 10, 0).dropped(1, list(range(10))) == []


def test_each_attack_alters_a_byzantine_upload_by_hand():
    """g = (1, 2) global, w = (2, 0) trained: sign_flip sends 2 g - w = (0, 4); scale 3
    sends g + 3 (w - g) = (4, -4); noise sends w + sigma N(0, 1), the same draw for the
    same seed, round and client; an honest client's upload and integer tensors pass."""
    g = {"w": torch.tensor([1.0, 2.0]), "steps": torch.tensor(5)}
    res = TrainRes(0, {"w": torch.tensor([2.0, 0.0]), "steps": torch.tensor(6)}, 10)

    def sent(**settings):
        return Faults(FaultsConfig(byzantine=1, **settings), clients=1, seed=0).sent(res, g, 3)

    assert sent(attack="sign_flip").weights["w"].tolist() == [0.0, 4.0]
    assert sent(attack="scale", scale=3.0).weights["w"].tolist() == [4.0, -4.0]
    noisy = sent(attack="noise", noise=0.5).weights["w"]
    assert torch.equal(noisy, sent(attack="noise", noise=0.5).weights["w"])
    z = (noisy - res.weights["w"]) / 0.5
    assert z.abs().max() > 0 and torch.isfinite(z).all()
    later = Faults(FaultsConfig(byzantine=1, attack="noise"), 1, 0).sent(res, g, 4).weights["w"]
    assert not torch.equal(later, noisy)  # another round, another draw
    assert sent(attack="sign_flip").weights["steps"].item() == 6
    honest = Faults(FaultsConfig(byzantine=1), clients=2, seed=0)
    (good,) = set(range(2)) - honest.byzantine
    mine = TrainRes(good, res.weights, 10)
    assert honest.sent(mine, g, 1) is mine


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("federated.faults.dropout=1.0", r"federated.faults.dropout=1.0: must be in \[0, 1\)"),
        (
            "federated.faults.byzantine=2",
            r"byzantine=2: fewer than data.clients=2",
        ),
        ("federated.faults.attack=lie", r"federated.faults.attack"),
        ("federated.faults.noise=-1", r"federated.faults.noise=-1.0: must be 0 or more"),
        ("federated.faults.straggler=1", r"federated.faults.straggler=1.0: must be in \[0, 1\)"),
        ("federated.faults.label=nan", r"federated.faults.label=nan"),
    ],
)
def test_impossible_faults_are_refused_at_load(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


def run(synth_dir, cache_dir, store, *overrides):
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        "data.modality=features",
        "data.clients=5",
        "federated.rounds=3",
        *overrides,
    )
    result = run_experiment(config)
    client = mlflow.MlflowClient(store)
    history = {
        key: [(m.step, m.value) for m in client.get_metric_history(result.run_id, key)]
        for key in (
            "faults/dropped",
            "faults/late",
            "round/participants",
            "faults/refused",
            "test/rmse",
        )
    }
    return result, client.get_run(result.run_id), history


def test_drop_outs_are_counted_each_round_and_the_same_for_a_seed(synth_dir, cache_dir, store):
    faults = Faults(FaultsConfig(dropout=0.4), clients=5, seed=0)
    expected = [(r, float(len(faults.dropped(r, list(range(5)))))) for r in (1, 2, 3)]
    assert any(n for _, n in expected)  # seed 0 drops someone in these rounds
    _, _, history = run(synth_dir, cache_dir, store, "federated.faults.dropout=0.4")
    assert history["faults/dropped"] == expected
    taken = [(r, 5 - n) for r, n in expected if n]
    assert history["round/participants"] == taken
    _, _, again = run(synth_dir, cache_dir, store, "federated.faults.dropout=0.4")
    assert again["test/rmse"] == history["test/rmse"]  # identical faults, identical run


def test_a_byzantine_client_scaling_its_update_is_refused_every_round(synth_dir, cache_dir, store):
    """attack=scale x 1e6: its update norm is a million times the others', so the server
    refuses it each round, names it, and the run's scores stay finite."""
    byzantine = Faults(FaultsConfig(byzantine=1), clients=5, seed=0).byzantine
    (bad,) = byzantine
    _, run_, history = run(
        synth_dir,
        cache_dir,
        store,
        "federated.faults.byzantine=1",
        "federated.faults.attack=scale",
        "federated.faults.scale=1e6",
    )
    assert history["faults/refused"] == [(1, 1.0), (2, 1.0), (3, 1.0)]
    # x1e6 drives a BatchNorm variance below 0 before its norm is measured
    assert run_.data.tags["fedlgr.not_taken"].startswith(
        f"round 1: client {bad} (upload: root.net.1.running_var holds variances below 0)"
    )
    assert all(math.isfinite(v) for _, v in history["test/rmse"])


def test_stragglers_are_drawn_from_the_seed_apart_from_drop_outs():
    """Late clients are drawn among those that train, from a stream of their own: adding
    stragglers changes no drop-out, and a seed gives the same ones."""
    both = Faults(FaultsConfig(dropout=0.3, straggler=0.3), clients=10, seed=0)
    alone = Faults(FaultsConfig(dropout=0.3), clients=10, seed=0)
    clients = list(range(10))
    for r in range(1, 21):
        assert both.dropped(r, clients) == alone.dropped(r, clients)
        what = both.what(r, clients)
        dropped = [c for c, f in what.items() if f == "dropped"]
        late = [c for c, f in what.items() if f == "late"]
        assert dropped == both.dropped(r, clients)
        assert late == both.late(r, [c for c in clients if c not in dropped])
        assert not set(late) & set(dropped)
    draws = [len(both.late(r, clients)) for r in range(1, 41)]
    assert 0.2 < sum(draws) / 400 < 0.4
    assert Faults(FaultsConfig(), 10, 0).late(1, clients) == []


@pytest.mark.slow
def test_a_straggler_trains_but_its_late_upload_is_dropped(synth_dir, cache_dir, store):
    """straggler=0.4 over 5 clients and 3 rounds (seed 0): the late clients are counted
    each round, trained (their training figures and upload bytes are in results.csv) and
    marked ``late``; their uploads are dropped, so the run differs from the clean one, and
    a second run is the same to the last digit."""
    faults = Faults(FaultsConfig(straggler=0.4), clients=5, seed=0)
    late = {r: faults.late(r, list(range(5))) for r in (1, 2, 3)}
    assert any(late.values()) and not all(len(v) == 5 for v in late.values())
    result, _, history = run(synth_dir, cache_dir, store, "federated.faults.straggler=0.4")
    assert history["faults/late"] == [(r, float(len(late[r]))) for r in (1, 2, 3)]
    assert history["faults/dropped"] == [] and history["round/participants"] == []
    client = mlflow.MlflowClient(store)
    for row in results_csv(client, result.run_id):
        was_late = int(row["client"]) in late[int(row["round"])]
        assert row["fault"] == ("late" if was_late else ""), row
        assert row["train_loss"] != "" and float(row["bytes_up"]) > 0
    _, _, again = run(synth_dir, cache_dir, store, "federated.faults.straggler=0.4")
    assert again["test/rmse"] == history["test/rmse"]
    _, _, clean = run(synth_dir, cache_dir, store)
    assert clean["test/rmse"] != history["test/rmse"]


def test_a_poisoned_client_trains_on_constant_labels(synth_dir, cache_dir, store):
    """attack=labels: the Byzantine client's training batches rate every action
    ``label``; the others' keep the scenes' ratings; results.csv marks it in every round
    it trained, and its honest-looking upload is aggregated (no refusal)."""
    from fedlgr.core.client.side import ClientSide  # lazy: torch models, this test only
    from fedlgr.shell.data.dataset import load_scenes  # lazy: as above
    from fedlgr.shell.data.splits import make_split  # lazy: as above

    settings = ["federated.faults.byzantine=1", "federated.faults.attack=labels"]
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        "data.modality=features",
        "data.clients=5",
        *settings,
        "federated.faults.label=4.5",
    )
    (bad,) = Faults(config.federated.faults, 5, config.seed).byzantine
    scenes = load_scenes(config.data)
    side = ClientSide(
        config, scenes, make_split(scenes.table, config.data), list(range(5)), torch.device("cpu")
    )
    for c in side.clients:
        [batches] = c.data.values()
        targets = batches.targets[batches.positions]
        if c.index == bad:
            assert torch.equal(targets, torch.full_like(targets, 4.5))
        else:
            assert targets.min() < 4.5 and len(targets.unique()) > 10
    result, _, history = run(synth_dir, cache_dir, store, *settings)
    assert history["faults/refused"] == []
    rows = results_csv(mlflow.MlflowClient(store), result.run_id)
    assert {(r["client"], r["fault"]) for r in rows} == {
        (str(c), "byzantine (labels)" if c == bad else "") for c in range(5)
    }
    _, _, clean = run(synth_dir, cache_dir, store)
    assert clean["test/rmse"] != history["test/rmse"]


def test_results_fault_column_says_what_went_wrong_with_each_client():
    """By hand: a simulated fault, a refusal (upload, scores or both) and a robot that
    sent nothing, each in its client's row; a client with none has an empty cell."""
    import numpy as np

    from fedlgr.core.records import RoundLog

    log = RoundLog(
        2,
        "all",
        ["test/rmse"],
        np.array([[0.5], [0.6], [np.nan], [np.nan], [0.7]]),
        1.0,
        missing=(2, 3),
        refused={1: "upload: update norm 9 is over 2 x the round's median 1", 2: "scores: x"},
        faults={0: "late", 1: "byzantine (scale)"},
    )
    assert [row["fault"] for row in log.rows()] == [
        "late",
        "byzantine (scale); refused upload: update norm 9 is over 2 x the round's median 1",
        "refused scores: x",
        "missing",
        "",
    ]


def test_the_serverapp_refuses_simulated_faults_itself():
    """fedlgr deploy run refuses faults where it can read the config; one submitted from a
    machine that does not hold CONFIG reaches the ServerApp, which refuses it before it
    speaks to any robot (it would otherwise run with no fault simulated, silently)."""
    from fedlgr.shell.deploy.flower.server_app import FlowerRounds  # lazy: flwr, this test

    config = load_config(None, ["deploy.roster=none", "federated.faults.dropout=0.5"])
    with pytest.raises(ConfigError, match=r"federated.faults: faults are simulated in one"):
        FlowerRounds(None, config)
