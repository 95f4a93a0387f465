"""Simulated faults (``federated.faults.*``): drop-outs and Byzantine clients, seeded,
on hand numbers and in runs whose rounds count them."""

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
from tests.support.runs import fast_config


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
        for key in ("faults/dropped", "round/participants", "faults/refused", "test/rmse")
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
    assert run_.data.tags["fedlgr.refused"].startswith(f"round 1: client {bad} (update norm")
    assert all(math.isfinite(v) for _, v in history["test/rmse"])
