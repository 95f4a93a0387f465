"""FedLGR's latent generative replay (``fedlgr.core.continual.lgr``): the two schedules, stored
replay, frozen root BatchNorm statistics, the replay's fidelity and its tracking - on tiny
models with hand-checkable numbers, and through fast runs of the real orchestrator."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from fedlgr.core.client.plugins import ClientPlugin, LocalContext
from fedlgr.core.client.training import Client, train_locally
from fedlgr.core.continual import continual_plugins
from fedlgr.core.continual.batchnorm import FrozenRootStatistics
from fedlgr.core.continual.fidelity import frechet_distance, replay_fidelity
from fedlgr.core.continual.lgr import LatentReplay, latents_of
from fedlgr.core.messages import RoundPlan, nbytes
from fedlgr.core.models.generator import LatentVAE
from fedlgr.core.models.scholar import build_scholar
from fedlgr.errors import ConfigError
from fedlgr.shell.config import load_config
from tests.support.lgr import (
    BN_BUFFERS,
    after_task_one,
    context,
    fedlgr_config,
    make_client,
    small_lgr,
    state,
    tiny_scholar,
)
from tests.support.runs import orchestrator, read_run, results_csv

pytestmark = pytest.mark.usefixtures("one_thread")


# --------------------------------------------------------------------------- tiny clients


class BatchNormSpy:
    """Every input of a BatchNorm layer, its mode and its running statistics before and
    after each call."""

    def __init__(self, bn: nn.BatchNorm1d):
        self.calls: list[dict] = []
        bn.register_forward_pre_hook(self.before)
        bn.register_forward_hook(self.after)

    def before(self, bn, args):
        self.calls.append(
            {
                "input": args[0].detach().clone(),
                "training": bn.training,
                "mean": bn.running_mean.clone(),
                "var": bn.running_var.clone(),
                "count": int(bn.num_batches_tracked),
            }
        )

    def after(self, bn, args, output):
        self.calls[-1] |= {
            "mean_after": bn.running_mean.clone(),
            "var_after": bn.running_var.clone(),
            "count_after": int(bn.num_batches_tracked),
        }


def check_running_statistics(call: dict, batch: torch.Tensor, momentum: float = 0.1) -> None:
    """PyTorch's update: new = (1 - m) old + m batch statistic (unbiased variance)."""
    expected_mean = (1 - momentum) * call["mean"] + momentum * batch.mean(dim=0)
    expected_var = (1 - momentum) * call["var"] + momentum * batch.var(dim=0, unbiased=True)
    assert torch.allclose(call["mean_after"], expected_mean, atol=1e-6)
    assert torch.allclose(call["var_after"], expected_var, atol=1e-5)
    assert call["count_after"] == call["count"] + 1


def identical(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# --------------------------------------------------------------------------- 1. one batch


def test_joint_top_batchnorm_sees_real_and_pseudo_latents_as_one_batch():
    lgr = small_lgr(schedule="joint", replay_ratio=2.0)
    client, ctx = after_task_one(lgr)
    model = client.model
    bn = model.top.net[0]
    assert bn.momentum == 0.1
    spy = BatchNormSpy(bn)  # after on_task_start: the labeller (a copy) has no spy
    reference = copy.deepcopy(model).train()
    rng = lgr.generator_rng.get_state()

    stats = train_locally(client, ctx, 1, max_batches=1)

    assert len(spy.calls) == 1 and spy.calls[0]["training"]
    x = client.batches.inputs[12:18]  # the first batch of task "b", in order
    with torch.no_grad():
        real = reference.root(x)  # training mode, like the client's root
    lgr.generator_rng.set_state(rng)
    pseudo = lgr.replayed_latents(12)  # replay_ratio 2 x 6 real samples
    union = torch.cat([real, pseudo])
    assert spy.calls[0]["input"].shape == (18, 6)
    assert torch.equal(spy.calls[0]["input"], union)
    check_running_statistics(spy.calls[0], union)
    assert stats.samples == 6  # the real samples; the pseudo-samples are not counted


def test_two_phase_top_batchnorm_sees_cached_and_pseudo_latents_as_one_batch():
    lgr = small_lgr(schedule="two_phase", replay_ratio=1.5)
    client, ctx = after_task_one(lgr, batch_size=4)
    model = client.model
    spy = BatchNormSpy(model.top.net[0])
    reference = copy.deepcopy(model)
    rng = lgr.generator_rng.get_state()

    stats = train_locally(client, ctx, 1)

    # The cached latents: the root in eval mode over one pass of the batches (in order).
    cached = latents_of(reference.root, client.batches)[0]
    assert not torch.equal(cached, reference.train().root(client.batches.inputs[12:24]))
    lgr.generator_rng.set_state(rng)
    order = torch.randperm(12, generator=lgr.generator_rng)
    top_phase = [c for c in spy.calls if c["training"]]
    assert len(top_phase) == 3  # 12 cached latents in batches of 4
    for k, call in enumerate(top_phase):
        pseudo = lgr.replayed_latents(6)  # 1.5 x 4
        union = torch.cat([cached[order[4 * k : 4 * k + 4]], pseudo])
        assert call["input"].shape == (10, 6)
        assert torch.equal(call["input"], union)
        check_running_statistics(call, union)
    # The root phase (3 batches) runs the top in eval mode: its statistics stay put.
    root_phase = spy.calls[3:]
    assert len(root_phase) == 3 and not any(c["training"] for c in root_phase)
    assert torch.equal(model.top.net[0].running_mean, top_phase[-1]["mean_after"])
    assert stats.samples == 12 + 12 and ctx.trained_samples == 12  # top phase + root phase


# --------------------------------------------------------------------------- 2. two phases


class Snapshot(ClientPlugin):
    """Records the model after the plugins before it started the round."""

    name = "snapshot"

    def on_round_start(self, ctx: LocalContext) -> None:
        self.root, self.top = state(ctx.model.root), state(ctx.model.top)
        self.top_grad = [p.requires_grad for p in ctx.model.top.parameters()]


def test_two_phase_trains_the_top_then_the_root_alone():
    lgr = small_lgr(schedule="two_phase", lr_root=1e-2)
    snap = Snapshot()
    client, ctx = after_task_one(lgr, snapshot=snap)
    root0, top0 = state(client.model.root), state(client.model.top)
    assert lgr.epochs(ctx, 1) == 1  # continual.lgr.root_epochs (default 1)

    train_locally(client, ctx, 1)

    # Phase 1 (on_round_start): the top moved, the root (weights and statistics) did not.
    assert identical(snap.root, root0)
    assert not torch.equal(snap.top["net.1.weight"], top0["net.1.weight"])
    assert not any(snap.top_grad)  # phase 2 freezes the top ...
    assert all(p.requires_grad for p in client.model.top.parameters())  # ... until round end
    # Phase 2 (the batch loop): the root alone, at lr_R; the top bit for bit as phase 1 left it.
    assert identical(state(client.model.top), snap.top)
    root1 = state(client.model.root)
    assert not torch.equal(root1["net.0.weight"], snap.root["net.0.weight"])
    assert not torch.equal(root1["net.1.running_mean"], snap.root["net.1.running_mean"])
    lr = {g["name"]: g["lr"] for g in client.optimizer.param_groups}
    assert lr == {"root": 1e-2, "top": 1e-3}


def test_two_phase_root_epochs_and_no_root_phase_at_lr_root_zero():
    lgr = small_lgr(schedule="two_phase", lr_root=0.0)
    client, ctx = after_task_one(lgr)
    assert lgr.epochs(ctx, 3) == 0  # the root would not move: no root phase
    root0, top0 = state(client.model.root), state(client.model.top)
    stats = train_locally(client, ctx, 3)
    assert identical(state(client.model.root), root0)  # no forward in training mode either
    assert not identical(state(client.model.top), top0)
    assert stats.samples == ctx.trained_samples == 12  # the top phase only
    expected = ctx.trained_loss / ctx.trained_samples
    assert stats.loss == pytest.approx(expected, rel=1e-6)

    # continual.lgr.root_epochs: the root phase's own epoch count (None: train.epochs).
    lgr2 = small_lgr(lr_root=1e-5, root_epochs=2)
    lgr2.tasks_learnt = 1
    assert lgr2.epochs(ctx, 3) == 2
    lgr2.root_epochs = None
    assert lgr2.epochs(ctx, 3) is None  # train.epochs
    lgr2.tasks_learnt = 0
    assert lgr2.epochs(ctx, 3) is None  # task 1 trains as FedRoot does


def test_two_phase_root_epochs_above_train_epochs_are_honoured():
    lgr = small_lgr(schedule="two_phase", lr_root=1e-2, root_epochs=3)
    client, ctx = after_task_one(lgr)
    assert lgr.epochs(ctx, 1) == 3
    stats = train_locally(client, ctx, 1)
    assert stats.samples - ctx.trained_samples == 3 * 12  # 3 root epochs over 12 scenes


def test_client_state_round_trip_keeps_the_generator_and_rng():
    lgr = small_lgr()
    client, _ = after_task_one(lgr)
    lgr2 = small_lgr(seed=99)
    client2 = make_client(lgr2)
    client2.load_state_dict(client.state_dict())
    assert lgr2.tasks_learnt == 1 and lgr2.generator is not None
    g1, g2 = lgr.generator.state_dict(), lgr2.generator.state_dict()
    assert identical(g1, g2)
    assert torch.equal(lgr.replayed_latents(5), lgr2.replayed_latents(5))  # same rng state


def test_client_state_round_trip_in_the_middle_of_a_task_keeps_the_labeller():
    lgr = small_lgr()
    client, _ = after_task_one(lgr)
    assert lgr.labeller is not None
    lgr2 = small_lgr()
    client2 = make_client(lgr2)
    client2.load_state_dict(client.state_dict())
    assert lgr2.labeller is None  # rebuilt from the saved state once a round starts
    lgr2.on_round_start(context(client2, 1))
    state = lgr.generator_rng.get_state()
    expected = lgr.pseudo_samples(4)
    lgr2.generator_rng.set_state(state)
    got = lgr2.pseudo_samples(4)
    assert torch.equal(got[0], expected[0]) and torch.equal(got[1], expected[1])


# --------------------------------------------------------------------------- 3. orchestrator


def root_batchnorm_buffers(client: Client) -> dict[str, torch.Tensor]:
    return {
        k: v.clone()
        for k, v in client.model.root.state_dict().items()
        if k.rsplit(".", 1)[-1] in BN_BUFFERS
    }


@pytest.mark.parametrize("freeze", [True, False])
def test_root_batchnorm_statistics_frozen_from_task_two(freeze, synth_dir, cache_dir, store):
    config = fedlgr_config(
        synth_dir,
        cache_dir,
        store,
        "tracking.enabled=false",
        f"continual.lgr.freeze_root_bn={str(freeze).lower()}",
    )
    assert config.continual.tasks == ("circle", "arrow")
    orch = orchestrator(config)
    kinds = [[type(p) for p in c.plugins] for c in orch.clients]
    assert len(kinds) == 2
    assert all((FrozenRootStatistics in k) == freeze and LatentReplay in k for k in kinds)

    orch.run_round(RoundPlan(1, 0, first_of_task=True, last_of_task=True))
    before = [root_batchnorm_buffers(c) for c in orch.clients]
    weights = [c.model.root.net[0].weight.detach().clone() for c in orch.clients]
    assert len(before[0]) == 3 * len(config.model.mlp_hidden)  # one BatchNorm per layer
    assert int(before[0]["net.1.num_batches_tracked"]) > 0  # task 1 updated them
    orch.run_round(RoundPlan(2, 1, first_of_task=True, last_of_task=True))
    after = [root_batchnorm_buffers(c) for c in orch.clients]

    for c, client in enumerate(orch.clients):
        # The root trained at lr_R in task 2 either way ...
        assert not torch.equal(client.model.root.net[0].weight, weights[c])
        # ... its statistics (aggregated too: they are root tensors) stayed put when frozen.
        same = [torch.equal(before[c][k], after[c][k]) for k in before[c]]
        assert all(same) if freeze else not any(same)


def test_continual_plugins_freeze_root_statistics_per_method():
    def kinds(*overrides):
        config = load_config(None, list(overrides))
        return [type(p).__name__ for p in continual_plugins(config.continual, 0, 0)]

    assert kinds("method=FedLGR") == ["FrozenRootStatistics", "LatentReplay"]
    assert kinds("method=FedLGR", "continual.lgr.freeze_root_bn=false") == ["LatentReplay"]
    assert kinds("method=FedRoot-EWC") == ["EWC"]
    assert kinds("method=FedRoot-EWC", "continual.freeze_root_bn=true") == [
        "FrozenRootStatistics",
        "EWC",
    ]
    # FedLGR answers to its own setting only.
    assert kinds(
        "method=FedLGR", "continual.freeze_root_bn=true", "continual.lgr.freeze_root_bn=false"
    ) == ["LatentReplay"]


def test_frozen_root_statistics_only_from_the_second_task():
    model = tiny_scholar().train()
    bn = model.root.net[1]
    ctx = LocalContext(0, 1, model, {}, torch.device("cpu"), task=0)
    FrozenRootStatistics().on_round_start(ctx)
    assert bn.training
    ctx.task = 1
    FrozenRootStatistics().on_round_start(ctx)
    assert not bn.training and model.root.training and model.top.net[0].training
    mean = bn.running_mean.clone()
    model(torch.randn(5, 4))
    assert torch.equal(bn.running_mean, mean) and int(bn.num_batches_tracked) == 0


# --------------------------------------------------------------------------- 4. fidelity


def test_replay_fidelity_is_zero_for_the_real_latents_and_grows_with_noise():
    g = torch.Generator().manual_seed(0)
    real = torch.randn(400, 5, generator=g) * torch.tensor([1.0, 2.0, 0.5, 3.0, 1.5]) + 4.0
    heldout = real[:80]
    noise = torch.randn(400, 5, generator=g)
    torch.manual_seed(0)
    labeller = nn.Linear(5, 8)
    perm = torch.randperm(400, generator=g)

    figures = []
    for std in (0.0, 0.5, 1.0):
        replayed = real[perm] + std * noise
        out = replay_fidelity(
            real, replayed, labeller, heldout, lambda h, s=std: h + s * noise[:80]
        )
        assert set(out) == {"fd_latent", "fd_labels", "recon_mse"}
        figures.append(out)
    for name in ("fd_latent", "fd_labels", "recon_mse"):
        values = [f[name] for f in figures]
        assert abs(values[0]) < 1e-6, (name, values)
        assert values[0] < values[1] < values[2], (name, values)
    # recon_mse: squared error per standardised feature, by hand.
    by_hand = ((noise[:80] / real.std(dim=0)) ** 2).mean()
    assert figures[2]["recon_mse"] == pytest.approx(float(by_hand), rel=1e-5)
    # Without a reconstruction (stored replay) there is no recon_mse.
    assert set(replay_fidelity(real, real, labeller)) == {"fd_latent", "fd_labels"}


def test_frechet_distance_matches_the_closed_form():
    # 1-D: (mu_a - mu_b)^2 + (sigma_a - sigma_b)^2, sample (unbiased) statistics.
    a = torch.tensor([[0.0], [1.0], [2.0], [3.0]])  # mean 1.5, variance 5/3
    b = 2 * a + 10  # mean 13, variance 20/3
    assert frechet_distance(a, b) == pytest.approx(11.5**2 + 5 / 3, rel=1e-12)
    assert frechet_distance(b, a) == pytest.approx(11.5**2 + 5 / 3, rel=1e-12)
    assert frechet_distance(a, a + 0.0) == pytest.approx(0.0, abs=1e-12)

    # 2-D, diagonal covariances: |dmu|^2 + sum (sigma_ai - sigma_bi)^2.
    a = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])  # mean 0, cov 2/3 I
    b = a * torch.tensor([2.0, 3.0]) + torch.tensor([1.0, -1.0])  # cov diag(8/3, 6)
    assert frechet_distance(a, b) == pytest.approx(2 + 2 / 3 * (1 + 4), rel=1e-12)

    # 2-D, general covariances: Tr((S_a S_b)^1/2) = sqrt(tr(S_a S_b) + 2 sqrt(det S_a det S_b)).
    g = torch.Generator().manual_seed(0)
    a = torch.randn(50, 2, generator=g, dtype=torch.float64) @ torch.tensor(
        [[1.0, 0.5], [0.0, 2.0]], dtype=torch.float64
    )
    b = torch.randn(60, 2, generator=g, dtype=torch.float64) @ torch.tensor(
        [[0.3, -1.0], [1.0, 0.2]], dtype=torch.float64
    ) + torch.tensor([1.0, 2.0], dtype=torch.float64)
    sa, sb = np.cov(a.numpy().T), np.cov(b.numpy().T)
    cross = math.sqrt(np.trace(sa @ sb) + 2 * math.sqrt(np.linalg.det(sa) * np.linalg.det(sb)))
    mean = float(((a.mean(0) - b.mean(0)) ** 2).sum())
    closed = mean + np.trace(sa) + np.trace(sb) - 2 * cross
    assert frechet_distance(a, b) == pytest.approx(closed, rel=1e-9)
    assert frechet_distance(b, a) == pytest.approx(closed, rel=1e-9)


# --------------------------------------------------------------------------- 6. early stop


def test_vae_fit_stops_early_and_keeps_the_best_epoch():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    # A small low-rank training set and held-out latents from elsewhere: the generator
    # overfits, the held-out loss stops improving.
    train = torch.relu(torch.randn(48, 3, generator=g) @ torch.randn(3, 12, generator=g))
    heldout = torch.rand(16, 12, generator=g) * 3
    vae = LatentVAE(12, hidden=32, latent=4, lr=1e-2)
    report = vae.fit(train, 300, 16, torch.Generator().manual_seed(1), heldout, patience=5)

    assert report.epochs < 300
    assert len(report.heldout) == len(report.train) == report.epochs
    best = min(report.heldout)
    assert report.best_epoch == report.heldout.index(best) + 1
    assert report.epochs == report.best_epoch + 5  # stopped 5 epochs without a gain
    assert report.heldout[-1] > best
    assert vae.heldout_loss(heldout) == pytest.approx(best, rel=1e-6)  # the best weights
    assert not vae.training

    # patience 0: every epoch runs, but the best weights are still the ones kept.
    vae = LatentVAE(12, hidden=32, latent=4, lr=1e-2)
    report = vae.fit(train, 30, 16, torch.Generator().manual_seed(1), heldout, patience=0)
    assert report.epochs == 30
    assert vae.heldout_loss(heldout) == pytest.approx(min(report.heldout), rel=1e-6)


def test_vae_reconstruct_and_sample_are_in_the_root_scale():
    g = torch.Generator().manual_seed(0)
    latents = torch.randn(64, 6, generator=g) * 5 + 100
    vae = LatentVAE(6, hidden=16, latent=2, lr=1e-3)
    vae.fit(latents, 1, 16, g)
    assert torch.allclose(vae.shift, latents.mean(0)) and torch.allclose(vae.scale, latents.std(0))
    with torch.no_grad():
        vae.eval()
        expected = vae(latents)[0] * vae.scale + vae.shift  # posterior mean, decoded
    assert torch.allclose(vae.reconstruct(latents), expected)
    assert (vae.sample(32, g).mean() - 100).abs() < 20


def test_posterior_sampler_draws_codes_like_the_training_codes():
    g = torch.Generator().manual_seed(0)
    latents = torch.relu(torch.randn(200, 3, generator=g) @ torch.randn(3, 10, generator=g))
    vae = LatentVAE(10, hidden=16, latent=3, lr=1e-2)
    vae.fit(latents, 20, 32, g)
    assert torch.equal(vae.code_mean, torch.zeros(3)) and torch.equal(vae.code_chol, torch.eye(3))
    vae.fit_code_density(latents)
    with torch.no_grad():
        codes = vae(latents)[1]  # posterior means (eval mode)
    assert torch.allclose(vae.code_mean.float(), codes.mean(0), atol=1e-5)
    cov = vae.code_chol.double() @ vae.code_chol.double().T
    assert torch.allclose(cov, torch.cov(codes.T.double()), atol=1e-4)
    # Samples are the decoded codes of N(mean, cov): with a fixed generator, by hand.
    eps = torch.randn(5, 3, generator=torch.Generator().manual_seed(4))
    z = vae.code_mean + eps @ vae.code_chol.T
    with torch.no_grad():
        expected = vae.decoder(z) * vae.scale + vae.shift
    assert torch.allclose(vae.sample(5, torch.Generator().manual_seed(4)), expected)
    vae.fit(latents, 1, 32, g)  # a new fit starts from the prior again
    assert torch.equal(vae.code_chol, torch.eye(3))


def test_a_client_of_one_training_latent_keeps_drawing_codes_from_the_prior():
    """A client that holds one scene of a task (small shards, issue 40): torch.cov of one
    code is NaN and its Cholesky failed; the prior stays and samples are finite."""
    g = torch.Generator().manual_seed(0)
    latents = torch.relu(torch.randn(1, 10, generator=g))
    vae = LatentVAE(10, hidden=16, latent=3, lr=1e-2)
    vae.fit(latents, 2, 32, g)
    vae.fit_code_density(latents)
    assert torch.equal(vae.code_mean, torch.zeros(3)) and torch.equal(vae.code_chol, torch.eye(3))
    assert torch.isfinite(vae.sample(4, torch.Generator().manual_seed(1))).all()


# --------------------------------------------------------------------------- 7. config


@pytest.mark.parametrize(
    "override, setting",
    [
        ("continual.lgr.schedule=bogus", "continual.lgr.schedule"),
        ("continual.lgr.replay=bogus", "continual.lgr.replay"),
        ("continual.lgr.holdout=1.0", "continual.lgr.holdout"),
        ("continual.lgr.holdout=-0.1", "continual.lgr.holdout"),
        ("continual.lgr.patience=-1", "continual.lgr.patience"),
        ("continual.lgr.root_epochs=-1", "continual.lgr.root_epochs"),
        ("continual.lgr.beta=-1", "continual.lgr.beta"),
    ],
)
def test_bad_lgr_settings_are_refused_by_name(override, setting):
    with pytest.raises(ConfigError, match=setting):
        load_config(None, ["method=FedLGR", override])


def test_lgr_settings_reach_the_plugin():
    config = load_config(
        None,
        [
            "method=FedLGR",
            "continual.lgr.schedule=joint",
            "continual.lgr.replay=stored",
            "continual.lgr.beta=0.5",
            "continual.lgr.patience=7",
            "continual.lgr.holdout=0.0",
            "continual.lgr.root_epochs=2",
            "continual.lgr.epochs=11",
        ],
    )
    (lgr,) = [p for p in continual_plugins(config.continual, 1, 0) if isinstance(p, LatentReplay)]
    assert (lgr.schedule, lgr.replay, lgr.beta, lgr.patience) == ("joint", "stored", 0.5, 7)
    assert (lgr.holdout, lgr.root_epochs, lgr.vae_epochs) == (0.0, 2, 11)
    # A bad value is refused where the config is loaded, naming the setting (the plugin
    # trusts the config it is given).
    with pytest.raises(
        ConfigError, match=r"continual\.lgr\.schedule=.bogus.: must be one of two_phase, joint"
    ):
        load_config(None, ["method=FedLGR", "continual.lgr.schedule=bogus"])


# --------------------------------------------------------------------------- 5, 8. tracked runs


@pytest.fixture(scope="module")
def synth96(tmp_path_factory) -> Path:
    """96 scenes: every client has >= 10 scenes per task, so the generator holds some out."""
    from fedlgr.shell.data.synth import synthesize

    out = tmp_path_factory.mktemp("synth96") / "d"
    synthesize(out, scenes=96, seed=7, size=16)
    return out


def tracked_config(synth96, cache, store, *overrides):
    return fedlgr_config(
        synth96,
        cache,
        store,
        "data.image_size=16",
        "continual.rounds_per_task=2",
        "tracking.detail_metrics=true",  # per-client metrics in MLflow too
        *overrides,
    )


@pytest.fixture(scope="module")
def generator_run(synth96, tmp_path_factory, store):
    from fedlgr.shell.run.experiment import run_experiment

    config = tracked_config(synth96, tmp_path_factory.mktemp("cache"), store)
    threads = torch.get_num_threads()
    result = run_experiment(config, echo=lambda *a, **k: None)  # sets runtime.threads=1
    torch.set_num_threads(threads)
    return config, result


@pytest.mark.slow
def test_stored_replay_uploads_the_root_only_and_keeps_past_latents(
    generator_run, synth96, cache_dir, store, monkeypatch
):
    from fedlgr.shell.run.experiment import run_experiment

    uploaded: set[str] = set()
    real_upload = Client.upload

    def upload(self, keys):
        uploaded.update(keys)
        return real_upload(self, keys)

    memories: dict[int, list[tuple[torch.Tensor, torch.Tensor]]] = {}
    real_end = LatentReplay.on_task_end

    def on_task_end(self, ctx):
        real_end(self, ctx)
        current = latents_of(ctx.model.root, ctx.plain_batches())[0]
        memories.setdefault(ctx.client, []).append((self.memory.clone(), current))

    monkeypatch.setattr(Client, "upload", upload)
    monkeypatch.setattr(LatentReplay, "on_task_end", on_task_end)
    config = tracked_config(synth96, cache_dir, store, "continual.lgr.replay=stored")
    result = run_experiment(config, echo=lambda *a, **k: None)

    root = build_scholar(config).root.state_dict()
    root_bytes = nbytes({k: v for k, v in root.items() if v.is_floating_point()})
    assert uploaded and all(k.startswith("root.") for k in uploaded)
    assert uploaded == {f"root.{k}" for k, v in root.items() if v.is_floating_point()}
    client, run, _ = read_run(store, result.run_id)
    generator_client, _, _ = read_run(store, generator_run[1].run_id)
    for c in (0, 1):
        key = f"cost/client{c}/bytes_up"
        ups = [m.value for m in client.get_metric_history(result.run_id, key)]
        generator_ups = [
            m.value for m in generator_client.get_metric_history(generator_run[1].run_id, key)
        ]
        assert ups == generator_ups == [root_bytes] * 4

    for c in (0, 1):
        (memory1, task1), (memory2, task2) = memories[c]
        assert torch.equal(memory1, task1)  # after task 1: exactly task 1's latents
        assert memory1.shape == (len(task1), config.model.mlp_hidden[-1])
        assert torch.equal(memory2, torch.cat([task1, task2]))  # then task 2's appended
    # The stored latents of task 1 are the real ones: a replay distance of ~0 after task 1.
    after1 = result.rounds[1]
    assert np.all(np.abs(after1.column("lgr_fd_latent")) < 1e-4)
    assert np.all(np.abs(after1.column("lgr_fd_labels")) < 1e-6)
    assert np.isnan(after1.column("lgr_recon_mse")).all()  # no generator: nothing to rebuild
    assert np.isnan(after1.column("lgr_vae_epochs")).all()
    assert run.data.params["continual.lgr.replay"] == "stored"


def test_fidelity_is_logged_at_task_ends_only(generator_run, store):
    config, result = generator_run
    client, run, _ = read_run(store, result.run_id)
    names = ("fd_latent", "recon_mse", "fd_labels", "vae_epochs")
    for key in [f"lgr/{n}" for n in names] + [f"lgr/client{c}/{n}" for c in (0, 1) for n in names]:
        history = client.get_metric_history(result.run_id, key)
        assert [m.step for m in history] == [2, 4], key  # rounds 2 and 4 end a task
        assert all(math.isfinite(m.value) and m.value >= 0 for m in history), key
    vae_epochs = [m.value for m in client.get_metric_history(result.run_id, "lgr/vae_epochs")]
    assert all(1 <= v <= config.continual.lgr.epochs for v in vae_epochs)

    rows = results_csv(client, result.run_id)
    assert "lgr_fd_latent" in rows[0] and "lgr_recon_mse" in rows[0]
    assert [bool(r["lgr_fd_latent"]) for r in rows] == [False] * 2 + [True] * 2 + [False] * 2 + [
        True
    ] * 2
    for r in rows:
        if r["lgr_fd_latent"]:
            key = f"lgr/client{r['client']}/fd_latent"
            logged = {m.step: m.value for m in client.get_metric_history(result.run_id, key)}
            assert float(r["lgr_fd_latent"]) == pytest.approx(logged[int(r["round"])])
    mean = np.mean([float(r["lgr_fd_latent"]) for r in rows if r["round"] == "4"])
    assert run.data.metrics["lgr/fd_latent"] == pytest.approx(mean)

    summary = result.summary()
    assert "replay fidelity" in summary
    assert "end of circle (round 2)" in summary and "end of arrow (round 4)" in summary
    assert "round 1)" not in summary and "round 3)" not in summary
