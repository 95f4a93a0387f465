"""FedLGR's drift controls (issue 19): the compensation map, feature distillation, partial
freezing of the root, and the drift figures logged at every round of a later task."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
from torch import nn

from fedlgr.core.client.plugins import LocalContext
from fedlgr.core.client.training import Client, train_locally
from fedlgr.core.continual import continual_plugins
from fedlgr.core.continual.drift import drift_distance, fit_drift_map
from fedlgr.core.continual.lgr import LatentReplay, latents_of
from fedlgr.core.messages import RoundPlan
from fedlgr.core.models.scholar import Scholar, Top
from fedlgr.core.scope import initial_scholar
from fedlgr.errors import ConfigError
from fedlgr.shell.config import MOBILENET_V2_BLOCKS, load_config
from tests.support.lgr import (
    BN_BUFFERS,
    after_task_one,
    fedlgr_config,
    small_lgr,
    state,
)
from tests.support.runs import orchestrator, read_run, results_csv

pytestmark = pytest.mark.usefixtures("one_thread")


# --------------------------------------------------------------------------- the map


def affine_drift(n: int, d: int, seed: int = 0):
    """``then`` (n x d), a drift ``M``, ``c`` and ``now = then M + c`` (float64)."""
    g = torch.Generator().manual_seed(seed)
    then = torch.randn(n, d, generator=g, dtype=torch.float64) * 2 + 1
    m = torch.eye(d, dtype=torch.float64) + 0.3 * torch.randn(
        d, d, generator=g, dtype=torch.float64
    )
    c = torch.randn(d, generator=g, dtype=torch.float64)
    return then, m, c, then @ m + c


def test_compensation_map_recovers_a_known_affine_drift_exactly():
    then, m, c, now = affine_drift(200, 8)
    mapping = fit_drift_map(then, now, ridge=0.0)  # more scenes than features: least squares
    torch.testing.assert_close(
        mapping.delta, m - torch.eye(8, dtype=torch.float64), atol=1e-10, rtol=0
    )
    torch.testing.assert_close(mapping(then), now, atol=1e-10, rtol=0)
    # Latents it was not fitted on (a past task's scenes) drift the same way.
    other = torch.randn(50, 8, dtype=torch.float64) * 3 - 2
    torch.testing.assert_close(mapping(other), other @ m + c, atol=1e-10, rtol=0)
    # float32 latents (the root's): the same map, to float32 rounding.
    mapping32 = fit_drift_map(then.float(), now.float(), ridge=0.0)
    assert mapping32.delta.dtype == torch.float32
    torch.testing.assert_close(
        mapping32(other.float()), (other @ m + c).float(), atol=2e-4, rtol=1e-4
    )


def test_compensation_map_with_fewer_scenes_than_features_leaves_the_rest_in_place():
    then, _, _, now = affine_drift(5, 12, seed=1)
    with pytest.raises(ValueError, match="ridge must be > 0 with 5 scenes for 12 features"):
        fit_drift_map(then, now, ridge=0.0)
    mapping = fit_drift_map(then, now, ridge=1e-9)  # the dual (5 x 5) form
    torch.testing.assert_close(mapping(then), now, atol=1e-6, rtol=0)  # the fitted scenes
    # A direction the 5 centred scenes do not span is not moved (shrunk to the identity):
    centred = then - then.mean(dim=0)
    basis = torch.linalg.svd(centred, full_matrices=True).Vh  # rows: right singular vectors
    unseen = basis[-1]  # orthogonal to every centred scene
    assert float((centred @ unseen).abs().max()) < 1e-10
    base = then.mean(dim=0, keepdim=True)
    moved = mapping(base + unseen) - mapping(base)
    torch.testing.assert_close(moved, unseen[None], atol=1e-8, rtol=0)


def test_a_large_ridge_leaves_only_the_mean_shift():
    then, _, _, now = affine_drift(200, 8, seed=2)
    mapping = fit_drift_map(then, now, ridge=1e9)
    shift = now.mean(dim=0) - then.mean(dim=0)
    torch.testing.assert_close(mapping(then), then + shift, atol=1e-6, rtol=0)


def test_drift_distance_is_zero_without_drift_and_grows_with_it():
    then, _, _, _ = affine_drift(300, 6, seed=3)
    assert drift_distance(then, then) < 1e-8
    # A shift by one standard deviation of every feature: ||mu||^2 = 6 once standardised.
    shifted = then + then.std(dim=0)
    assert drift_distance(shifted, then) == pytest.approx(6.0, rel=1e-6)


# --------------------------------------------------------------------------- distillation


def linear_scholar(weight: list[list[float]], bias: list[float]) -> Scholar:
    root = nn.Linear(3, 2)
    with torch.no_grad():
        root.weight.copy_(torch.tensor(weight))
        root.bias.copy_(torch.tensor(bias))
    return Scholar(root, Top(2, hidden=4)).eval()


def plain_context(model: Scholar) -> LocalContext:
    return LocalContext(0, 1, model, {}, torch.device("cpu"), task=1)


def distill_loss(lgr: LatentReplay, model: Scholar, x: torch.Tensor) -> torch.Tensor:
    ctx = plain_context(model)
    outputs, y = lgr.forward(ctx, x, torch.zeros(len(x), 8))
    return lgr.loss(ctx, x, y, outputs, torch.zeros(()))


def test_distillation_is_zero_at_the_task_start_and_has_the_hand_gradient():
    lgr = LatentReplay(drift="distill", distill_weight=3.0)
    lgr.tasks_learnt = 1  # a later task: replaying
    model = linear_scholar([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], [0.5, -0.5])
    lgr.on_task_start(plain_context(model))
    x = torch.tensor([[2.0, 1.0, 1.0]])

    at_start = distill_loss(lgr, model, x)
    assert float(at_start.detach()) == 0.0
    at_start.backward()
    assert torch.equal(model.root.weight.grad, torch.zeros(2, 3))

    # The root moves: W[0, 0] 1 -> 1.5, so root(x) - root_0(x) = [0.5 x 2, 0] = [1, 0].
    model.root.weight.grad = None
    with torch.no_grad():
        model.root.weight[0, 0] = 1.5
    loss = distill_loss(lgr, model, x)
    assert float(loss.detach()) == pytest.approx(
        3.0 * (1.0**2 + 0.0**2) / 2
    )  # weight x mean square
    loss.backward()
    # d/dW of 3 x mean((W x + b - r0)^2) over 2 features = 3 x 2/2 x (r - r0) x^T
    expected = torch.tensor([[6.0, 3.0, 3.0], [0.0, 0.0, 0.0]])
    torch.testing.assert_close(model.root.weight.grad, expected)
    torch.testing.assert_close(model.root.bias.grad, torch.tensor([3.0, 0.0]))
    assert lgr.root_start.weight[0, 0] == 1.0  # the task-start copy did not move


def test_without_distillation_the_root_phase_adds_nothing():
    lgr = LatentReplay(drift="none")
    lgr.tasks_learnt = 1
    model = linear_scholar([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], [0.0, 0.0])
    ctx = plain_context(model)
    lgr.on_task_start(ctx)
    x = torch.ones(1, 3)
    assert lgr.forward(ctx, x, torch.zeros(1, 8)) is None  # two_phase, phase 2: the model's own
    loss = torch.tensor(0.25)
    assert lgr.loss(ctx, x, None, None, loss) is loss


def test_the_task_start_root_survives_a_checkpoint_in_the_middle_of_a_task():
    lgr = small_lgr(drift="distill")
    client, ctx = after_task_one(lgr)
    start = state(lgr.root_start)
    saved = copy.deepcopy(lgr.state_dict())
    train_locally(client, ctx, 1)  # a round of task "b": the root moves
    restored = small_lgr(drift="distill")
    restored.load_state_dict(saved)
    assert restored.root_start is None  # until a model is at hand
    restored.on_round_start(ctx)
    assert all(torch.equal(v, start[k]) for k, v in restored.root_start.state_dict().items())


# --------------------------------------------------------------------------- compensation


def nearest(rows: torch.Tensor, among: torch.Tensor) -> torch.Tensor:
    """Each row's distance to the nearest row of ``among`` (exact differences, no mm)."""
    return torch.cdist(rows, among, compute_mode="donot_use_mm_for_euclid_dist").min(dim=1).values


def test_stored_latents_are_carried_into_the_new_space_at_the_task_end():
    lgr = small_lgr(replay="stored", drift="compensate", compensate_ridge=0.5)
    client, ctx = after_task_one(lgr)
    memory = lgr.memory.clone()
    start = latents_of(lgr.root_start, ctx.plain_batches())[0]
    with torch.no_grad():  # drift: the root as aggregation might leave it
        for p in client.model.root.parameters():
            p.add_(0.05 * torch.randn_like(p))
    now = latents_of(client.model.root, ctx.plain_batches())[0]
    lgr.on_task_end(ctx)

    carry = fit_drift_map(start, now, 0.5)
    assert lgr.memory.shape == (len(memory) + len(now), memory.shape[1])
    torch.testing.assert_close(lgr.memory[: len(memory)], carry(memory))
    assert not torch.allclose(lgr.memory[: len(memory)], memory, atol=1e-3)  # it did move
    assert torch.equal(lgr.memory[len(memory) :], now)


def test_compensation_maps_the_replayed_latents_but_labels_the_old_ones():
    lgr = small_lgr(replay="stored", drift="compensate")
    client, ctx = after_task_one(lgr)
    with torch.no_grad():
        for p in client.model.root.parameters():
            p.add_(0.05 * torch.randn_like(p))
    seen = []
    top = client.model.top
    hook = top.register_forward_pre_hook(lambda m, args: seen.append(args[0].detach().clone()))
    lgr.on_round_start(ctx)  # fits the map, then trains the top on R U map(R')
    hook.remove()
    assert lgr.drift_map.delta.shape == (lgr.memory.shape[1],) * 2
    # Every replayed row the top saw is the map of a stored latent, not a stored one.
    mapped = lgr.drift_map(lgr.memory)
    replayed = torch.cat([s[s.shape[0] // 5 :] for s in seen])  # ratio 4: 4/5 of each batch
    near_mapped = nearest(replayed, mapped)
    near_stored = nearest(replayed, lgr.memory)
    assert float(near_mapped.max()) < 1e-5 < float(near_stored.min())


# --------------------------------------------------------------------------- partial freezing


@pytest.mark.slow
@pytest.mark.parametrize(
    ("modality", "overrides", "frozen", "trained"),
    [
        (
            "features",
            ["model.mlp_hidden=[16,16]", "continual.lgr.train_blocks=1"],
            ["net.0.", "net.1."],
            ["net.3."],
        ),
        (
            "image",
            ["continual.lgr.train_blocks=2"],
            [f"features.{i}." for i in range(17)],
            ["features.17.", "features.18."],
        ),
    ],
)
def test_frozen_blocks_are_bit_identical_after_a_task_two_round(
    modality, overrides, frozen, trained, synth_dir, cache_dir, store, monkeypatch
):
    uploaded: set[str] = set()
    real_upload = Client.upload

    def upload(self, keys):
        uploaded.update(keys)
        return real_upload(self, keys)

    monkeypatch.setattr(Client, "upload", upload)
    config = fedlgr_config(
        synth_dir,
        cache_dir,
        store,
        "tracking.enabled=false",
        f"data.modality={modality}",
        "continual.lgr.lr_root=0.01",  # far beyond rounding
        "continual.lgr.freeze_root_bn=false",  # the trained blocks' statistics move too
        *overrides,
    )
    orch = orchestrator(config)
    orch.run_round(RoundPlan(1, 0, first_of_task=True, last_of_task=True))
    before = [state(c.model.root) for c in orch.clients]
    orch.run_round(RoundPlan(2, 1, first_of_task=True, last_of_task=False))
    after = [state(c.model.root) for c in orch.clients]

    for b, a in zip(before, after, strict=True):
        kept = [k for k in b if any(k.startswith(p) for p in frozen)]
        moved = [k for k in b if any(k.startswith(p) for p in trained)]
        assert kept and moved
        assert any(k.rsplit(".", 1)[-1] in BN_BUFFERS for k in kept)  # statistics too
        assert all(torch.equal(a[k], b[k]) for k in kept)  # after aggregation, bit for bit
        assert not any(torch.equal(a[k], b[k]) for k in moved if a[k].is_floating_point())
    assert uploaded and all(k.startswith("root.") for k in uploaded)  # the root alone
    root = orch.clients[0].model.root
    assert all(p.requires_grad for p in root.parameters())  # left as the round found them


# --------------------------------------------------------------------------- settings, figures


@pytest.mark.parametrize(
    ("override", "setting"),
    [
        ("continual.lgr.drift=bogus", "continual.lgr.drift"),
        ("continual.lgr.train_blocks=-1", "continual.lgr.train_blocks"),
        ("continual.lgr.distill_weight=-1", "continual.lgr.distill_weight"),
        ("continual.lgr.compensate_ridge=-1", "continual.lgr.compensate_ridge"),
        ("continual.lgr.compensate_ridge=0", "continual.lgr.compensate_ridge=0.0: must be > 0"),
    ],
)
def test_bad_drift_settings_are_refused_by_name(override, setting):
    with pytest.raises(ConfigError, match=setting):
        load_config(None, ["method=FedLGR", override])


@pytest.mark.parametrize(
    ("overrides", "said"),
    [
        (
            ["data.modality=features", "model.mlp_hidden=[16]", "continual.lgr.train_blocks=2"],
            "continual.lgr.train_blocks=2: the root (model.mlp_hidden=[16]) has 1 block; at "
            "most 1 (null: the whole root trains)",
        ),
        (
            ["continual.lgr.train_blocks=20"],
            "continual.lgr.train_blocks=20: the root (MobileNetV2) has 19 blocks; at most 19",
        ),
    ],
)
def test_more_trained_blocks_than_the_root_has_are_refused(overrides, said):
    """It trained the whole root without a word before."""
    with pytest.raises(ConfigError) as caught:
        load_config(None, ["method=FedLGR", *overrides])
    assert said in str(caught.value)


def test_the_block_counts_the_config_checks_are_the_models():
    mlp = load_config(None, ["data.modality=features", "model.mlp_hidden=[16,8,4]"])
    assert len(initial_scholar(mlp).root.blocks()) == 3
    image = load_config(None, ["model.width=0.35"])
    assert len(initial_scholar(image).root.blocks()) == MOBILENET_V2_BLOCKS == 19


def test_drift_settings_reach_the_plugin():
    config = load_config(
        None,
        [
            "method=FedLGR",
            "continual.lgr.drift=compensate+distill",
            "continual.lgr.compensate_ridge=0.25",
            "continual.lgr.distill_weight=7",
            "continual.lgr.train_blocks=3",
        ],
    )
    (lgr,) = [p for p in continual_plugins(config.continual, 1, 0) if isinstance(p, LatentReplay)]
    assert (lgr.compensate, lgr.distill) == (True, True)
    assert (lgr.compensate_ridge, lgr.distill_weight, lgr.train_blocks) == (0.25, 7.0, 3)


@pytest.mark.slow
def test_drift_figures_are_logged_at_every_round_of_a_later_task(synth_dir, cache_dir, store):
    from fedlgr.shell.run.experiment import run_experiment

    config = fedlgr_config(
        synth_dir,
        cache_dir,
        store,
        "tracking.detail_metrics=true",  # per-client metrics in MLflow too
        "continual.rounds_per_task=2",
        "continual.lgr.drift=compensate",
        "continual.lgr.lr_root=0.01",
    )
    result = run_experiment(config, echo=lambda *a, **k: None)
    client, run, _ = read_run(store, result.run_id)
    names = ("drift", "drift_residual", "drift_past", "drift_past_residual")
    rows = results_csv(client, result.run_id)
    for r in rows:
        later = r["task"] == "arrow"
        assert [bool(r[f"lgr_{n}"]) for n in names] == [later] * 4, r
    for n in names:
        for c in (0, 1):
            history = client.get_metric_history(result.run_id, f"lgr/client{c}/{n}")
            assert [m.step for m in history] == [3, 4], n  # task 2's rounds
            assert all(math.isfinite(m.value) and m.value >= 0 for m in history)
    for r in rows:
        if r["task"] == "arrow":  # on the scenes it was fitted on, the map reduces the drift
            assert float(r["lgr_drift_residual"]) < float(r["lgr_drift"])
    last = [float(r["lgr_drift"]) for r in rows if r["round"] == "4"]
    assert run.data.metrics["lgr/drift"] == pytest.approx(np.mean(last))
    assert min(last) > 0.01  # lr_R 0.01: the root moved
    summary = result.summary()
    assert "latent drift since the task's start" in summary
    assert (
        "round 3 (arrow)" in summary and "round 2 (circle)" not in summary.split("latent drift")[1]
    )


# ------------------------------------------------------------- replay at the freeze point


def test_replay_at_the_freeze_point_keeps_the_activations_entering_the_trained_blocks():
    # The tiny MLP root has one block: with it training, the freeze point is the input.
    lgr = small_lgr(replay="stored", replay_layer="freeze", train_blocks=1, schedule="joint")
    client, ctx = after_task_one(lgr)
    scenes = client.data["a"].inputs[client.data["a"].positions]
    assert torch.equal(lgr.memory, scenes)  # the activations entering block 0: the scenes
    start_model = copy.deepcopy(client.model).eval()

    x, y = next(iter(ctx.batches))
    lgr.on_round_start(ctx)
    outputs, targets = lgr.forward(ctx, x, y)
    n = round(len(x) * lgr.replay_ratio)
    assert outputs.shape == targets.shape == (len(x) + n, 8)
    assert torch.equal(targets[: len(x)], y)
    # The pseudo-labels are the task-start model's outputs on the replayed activations.
    replayed = targets[len(x) :]
    with torch.no_grad():
        every = start_model(lgr.memory)
    assert float(nearest(replayed, every).max()) < 1e-5
    lgr.on_round_end(ctx)


def test_replay_at_the_freeze_point_needs_trained_blocks_and_the_joint_schedule():
    message = "continual.lgr.replay_layer=freeze .* not continual.lgr.train_blocks=None"
    with pytest.raises(ConfigError, match=message):
        load_config(
            None,
            [
                "method=FedLGR",
                "continual.lgr.replay_layer=freeze",
                "continual.lgr.train_blocks=null",
                "continual.lgr.schedule=joint",
            ],
        )
    with pytest.raises(
        ConfigError,
        match=r"schedule=joint and no compensation, not continual\.lgr\.schedule=two_phase$",
    ):
        load_config(
            None,
            ["method=FedLGR", "continual.lgr.replay_layer=freeze", "continual.lgr.train_blocks=2"],
        )
    config = load_config(
        None,
        [
            "method=FedLGR",
            "continual.lgr.replay_layer=freeze",
            "continual.lgr.train_blocks=2",
            "continual.lgr.schedule=joint",
        ],
    )
    (lgr,) = [p for p in continual_plugins(config.continual, 1, 0) if isinstance(p, LatentReplay)]
    assert (lgr.replay_layer, lgr.train_blocks, lgr.schedule) == ("freeze", 2, "joint")
