"""Batched client training (fedlgr/core/batched.py) against sequential ``train_locally``.

Each test builds real clients with :class:`ClientSide` on the synthetic data, copies them,
trains one copy client after client with ``train_locally`` and the other with
``train_batched``, and compares everything the clients keep.

Why most comparisons run in float64: the fast config's MobileNetV2 (width 0.1, 32 px)
normalises 8 samples of 1x1 feature maps, which amplifies float32 rounding ~1e4-fold in
one forward pass (two *sequential* runs that differ only in memory layout already
disagree by 7e-4 in the outputs); and Adam turns the pure rounding noise in the gradients
of parameters whose true gradient is zero (a bias followed by a BatchNorm) into steps of
+-lr. After a few float32 steps both paths are equally right and far apart, so a float32
comparison over several steps could only use tolerances that would also pass a broken
implementation. In float64 (models and inputs; the loss is still taken in float32, as
``train_locally`` does) both effects shrink to ~1e-8, so the tolerances below are tight.
One float32 test covers the production dtype on a single step, before any amplification.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from fedlgr.core.client import stacked as batched
from fedlgr.core.client.side import ClientSide
from fedlgr.core.client.stacked import train_batched
from fedlgr.core.client.training import Client, train_locally
from fedlgr.core.data.augment import Augment, SceneBatches
from fedlgr.errors import FedlgrError
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.splits import make_split
from tests.support.float64 import Float64Batches, assert_close_f64
from tests.support.runs import fast_config

pytestmark = pytest.mark.usefixtures("one_thread")


def client_side(synth_dir, cache_dir, store, *overrides) -> ClientSide:
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        "data.clients=3",
        "data.augment=true",  # augmentation draws from each client's generator
        *overrides,
    )
    scenes = load_scenes(config.data)
    split = make_split(scenes.table, config.data)
    return ClientSide(config, scenes, split, [0, 1, 2], torch.device("cpu"))


def in_float64(clients: list[Client]) -> list[Client]:
    for c in clients:
        c.model.double()  # in place: the optimiser keeps the same parameter objects
        c.data = {t: Float64Batches(b) for t, b in c.data.items()}
    return clients


def both_ways(side: ClientSide, clients: list[Client], epochs: int, max_batches, on_epoch=None):
    """(sequential clients, their stats, batched clients, their stats) from copies."""
    seq, bat = copy.deepcopy(clients), copy.deepcopy(clients)
    seq_stats = [
        train_locally(c, side.context(c, 1, 0), epochs, max_batches, side.channels_last)
        for c in seq
    ]
    ctxs = [side.context(c, 1, 0) for c in bat]
    bat_stats = train_batched(bat, ctxs, epochs, max_batches, side.channels_last, on_epoch=on_epoch)
    return seq, seq_stats, bat, bat_stats


def record_steps(monkeypatch) -> dict[str, list]:
    """Group sizes of the stacked steps and clients of the plain steps, as they run."""
    seen = {"stacked": [], "plain": []}
    stacked, plain = batched._batched_step, batched._plain_step

    def stacked_step(template, members, xs, ys, autocast):
        seen["stacked"].append(len(members))
        return stacked(template, members, xs, ys, autocast)

    def plain_step(client, x, y, autocast):
        seen["plain"].append(client.index)
        return plain(client, x, y, autocast)

    monkeypatch.setattr(batched, "_batched_step", stacked_step)
    monkeypatch.setattr(batched, "_plain_step", plain_step)
    return seen


def assert_same_clients(seq: list[Client], bat: list[Client]) -> None:
    for a, b in zip(seq, bat, strict=True):
        sa, sb = a.model.state_dict(), b.model.state_dict()
        assert sa.keys() == sb.keys()
        for key in sa:
            assert_close_f64(sb[key], sa[key], msg=lambda m, k=key: f"{k}: {m}")
        for (n, p), q in zip(a.model.named_parameters(), b.model.parameters(), strict=True):
            for name in ("exp_avg", "exp_avg_sq", "step"):
                assert_close_f64(
                    b.optimizer.state[q][name],
                    a.optimizer.state[p][name],
                    msg=lambda m, k=f"{n} {name}": f"{k}: {m}",
                )
        for task in a.data:
            assert torch.equal(
                a.data[task].generator.get_state(), b.data[task].generator.get_state()
            )


def assert_trained(before: list[Client], after: list[Client]) -> None:
    """Training moved every client's weights far beyond the comparison's tolerance."""
    for b, a in zip(before, after, strict=True):
        w0, w1 = b.model.state_dict(), a.model.state_dict()
        assert max((w1[k] - w0[k].to(w1[k].dtype)).abs().max() for k in w0) > 1e-4


# 12 scenes per client, 2 augmented copies (images flipped and rotated, descriptors with
# input noise): 3 batches of 8 per epoch, of which max_batches=2 train; the third is drawn
# (and its augmentation) as train_locally does.
@pytest.mark.slow
@pytest.mark.parametrize(("modality", "samples"), [("image", 32), ("features", 32)])
def test_batched_training_ends_where_sequential_training_ends(
    modality, samples, synth_dir, cache_dir, store, monkeypatch
):
    side = client_side(
        synth_dir, cache_dir, store, f"data.modality={modality}", "data.augment_copies=2"
    )
    clients = in_float64(side.clients)
    steps = record_steps(monkeypatch)
    epochs_done = []
    seq, seq_stats, bat, bat_stats = both_ways(
        side, clients, 2, 2, on_epoch=lambda e: epochs_done.append(e)
    )

    assert steps == {"stacked": [3, 3, 3, 3], "plain": []}  # all 3 clients in every step
    assert epochs_done == [1, 2]  # once per epoch for all the clients
    assert_trained(clients, bat)
    assert_same_clients(seq, bat)
    assert [s.samples for s in bat_stats] == [s.samples for s in seq_stats] == [samples] * 3
    for s, b in zip(seq_stats, bat_stats, strict=True):
        assert b.loss == pytest.approx(s.loss, rel=1e-6)  # per-step losses are float32


@pytest.mark.slow
def test_ragged_clients_stack_where_their_batches_match(synth_dir, cache_dir, store, monkeypatch):
    side = client_side(synth_dir, cache_dir, store)
    clients = in_float64(side.clients)
    # 13, 21 and 17 scenes in batches of 8: [8, 5], [8, 8, 5], [8, 8, 1] per epoch.
    starts, sizes = (0, 13, 27), (13, 21, 17)
    for c, start, size in zip(clients, starts, sizes, strict=True):
        old = c.batches.batches
        positions = np.arange(start, start + size)
        ragged = SceneBatches(
            old.inputs, old.targets, positions, 8, augment=Augment(), seed=100 + c.index
        )
        c.data = {c.task: Float64Batches(ragged)}
    steps = record_steps(monkeypatch)
    seq, seq_stats, bat, bat_stats = both_ways(side, clients, 2, None)

    # Per epoch: step 1 stacks all three; step 2 stacks clients 1 and 2 (8 each) and runs
    # client 0's 5 alone; step 3 runs client 1's 5 alone and skips client 2's single scene.
    assert steps == {"stacked": [3, 2, 3, 2], "plain": [0, 1, 0, 1]}
    assert [s.samples for s in bat_stats] == [s.samples for s in seq_stats] == [26, 42, 32]
    assert_trained(clients, bat)
    assert_same_clients(seq, bat)
    for s, b in zip(seq_stats, bat_stats, strict=True):
        assert b.loss == pytest.approx(s.loss, rel=1e-6)


def test_one_float32_step_matches(synth_dir, cache_dir, store):
    """The production dtype (float32, channels-last images, fused Adam) on one step: the
    running statistics, gradients, Adam moments and losses agree to float32 rounding."""
    side = client_side(synth_dir, cache_dir, store)
    assert side.channels_last
    seq, seq_stats, bat, bat_stats = both_ways(side, side.clients, 1, 1)

    for s, b in zip(seq_stats, bat_stats, strict=True):
        assert b.samples == s.samples == 8
        assert b.loss == pytest.approx(s.loss, rel=1e-5)
    for a, b in zip(seq, bat, strict=True):
        buffers = dict(a.model.named_buffers())
        for name, buffer in b.model.named_buffers():  # updated by the forward pass
            torch.testing.assert_close(buffer, buffers[name], rtol=1e-4, atol=1e-5)
        # Gradients of weights whose true gradient is 0 (a bias before a BatchNorm) are
        # rounding noise (~1e-6 of the largest): compare at a scale set by the largest.
        scale = max(p.grad.abs().max() for p in a.model.parameters())
        for p, q in zip(a.model.parameters(), b.model.parameters(), strict=True):
            torch.testing.assert_close(q.grad, p.grad, rtol=1e-3, atol=1e-4 * scale)
            torch.testing.assert_close(
                b.optimizer.state[q]["exp_avg"],
                a.optimizer.state[p]["exp_avg"],
                rtol=1e-3,
                atol=1e-4 * scale,
            )


def test_clients_with_plugins_are_refused_untouched(synth_dir, cache_dir, store):
    side = client_side(synth_dir, cache_dir, store, "method=FedProx")
    assert all(c.plugins for c in side.clients)
    before = copy.deepcopy(side.clients)
    ctxs = [side.context(c, 1, 0) for c in side.clients]
    with pytest.raises(FedlgrError) as error:
        train_batched(side.clients, ctxs, 1, 1, side.channels_last)
    message = str(error.value)
    assert message.startswith("runtime.concurrency=batched trains clients without plugins only")
    assert "client 0 (fedprox); client 1 (fedprox); client 2 (fedprox)" in message
    assert message.endswith("use runtime.concurrency=threads or sequential")
    for a, b in zip(before, side.clients, strict=True):
        assert all(torch.equal(v, b.model.state_dict()[k]) for k, v in a.model.state_dict().items())
        assert torch.equal(a.batches.generator.get_state(), b.batches.generator.get_state())


def test_a_non_finite_loss_names_the_client(synth_dir, cache_dir, store):
    side = client_side(synth_dir, cache_dir, store, "data.modality=features")
    with torch.no_grad():
        side.clients[1].model.top.net[-1].bias.fill_(float("inf"))
    ctxs = [side.context(c, 1, 0) for c in side.clients]
    with pytest.raises(FedlgrError, match=r"round 1, client 1: the training loss is (nan|inf)"):
        train_batched(side.clients, ctxs, 1, 1)
