"""Continual-learning methods on tiny models with hand-checkable numbers."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from fedlgr.core.client.plugins import LocalContext
from fedlgr.core.client.training import Client, train_locally
from fedlgr.core.continual import continual_plugins
from fedlgr.core.continual.ewc import EWC, EWCOnline, fisher
from fedlgr.core.continual.lgr import LatentReplay
from fedlgr.core.continual.lwf import LwF
from fedlgr.core.continual.mas import MAS, output_norm_importance
from fedlgr.core.continual.rehearsal import NaiveRehearsal
from fedlgr.core.continual.si import SI
from fedlgr.core.data.augment import SceneBatches
from fedlgr.core.models.generator import LatentVAE
from fedlgr.core.models.scholar import MLPRoot, Scholar, Top
from fedlgr.shell.config import load_config
from tests.support.lgr import context as lgr_context

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny tensors: one thread is fastest, and immune to other processes' load (two threads
    on a busy two-core machine slow the VAE fit down 20-fold)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def linear(w, b=0.0) -> nn.Linear:
    model = nn.Linear(len(w), 1)
    with torch.no_grad():
        model.weight.copy_(torch.tensor([w]))
        model.bias.fill_(b)
    return model


def context(
    model, inputs, targets, positions=None, task=0, batch_size=1, optimizer=None
) -> LocalContext:
    positions = np.arange(len(inputs)) if positions is None else np.asarray(positions)
    batches = SceneBatches(inputs, targets, positions, batch_size, shuffle=False)
    return LocalContext(
        0, 1, model, {}, torch.device("cpu"), task=task, batches=batches, optimizer=optimizer
    )


X = torch.tensor([[1.0, 2.0], [3.0, -1.0]])
Y = torch.tensor([[0.0], [1.0]])


# The 2-parameter model out = w x + b at w = 0.5, b = 0 on three scenes: x = (1, 2, -1),
# y = (0, 2, 1); outputs (0.5, 1, -0.5), errors out - y = (0.5, -1, -1.5).
X3 = torch.tensor([[1.0], [2.0], [-1.0]])
Y3 = torch.tensor([[0.0], [2.0], [1.0]])


def test_empirical_fisher_is_the_mean_of_each_scenes_squared_gradient():
    """Kirkpatrick et al. 2017: F = mean over scenes of (d loss_n / d theta)^2. Each scene's
    MSE gradient is 2 e (x, 1): (1, 1), (-4, -2), (3, -3), whatever the batch size."""
    model = linear([0.5])
    for batch_size in (1, 2, 3):
        f = fisher(model, context(model, X3, Y3, batch_size=batch_size).plain_batches())
        assert f["weight"].item() == pytest.approx((1 + 16 + 9) / 3, rel=1e-6)
        assert f["bias"].item() == pytest.approx((1 + 4 + 9) / 3, rel=1e-6)


def test_batch_fisher_is_the_form_before_issue_48():
    """fisher=batch: the squared gradient of each mini-batch's mean loss, averaged over
    batches. Batches of 2: {1, 2} has gradient ((1 - 4) / 2, (1 - 2) / 2) = (-1.5, -0.5),
    {3} has (3, -3): F = ((2.25 + 9) / 2, (0.25 + 9) / 2) - not the per-scene (26/3, 14/3)."""
    model = linear([0.5])
    f = fisher(model, context(model, X3, Y3, batch_size=2).plain_batches(), "batch")
    assert f["weight"].item() == pytest.approx(5.625, rel=1e-6)
    assert f["bias"].item() == pytest.approx(4.625, rel=1e-6)


def test_fisher_of_a_two_input_model_by_hand():
    model = linear([0.5, -1.0])
    f = fisher(model, context(model, X, Y, batch_size=2).plain_batches())
    # Sample 1: out -1.5, d MSE/dw = 2 (out - y) x = (-3, -6), d/db = -3.
    # Sample 2: out 2.5, error 1.5: (9, -3), 3. Fisher = mean of squares.
    assert f["weight"].flatten().tolist() == pytest.approx([(9 + 81) / 2, (36 + 9) / 2])
    assert f["bias"].tolist() == pytest.approx([(9 + 9) / 2])


def test_model_fisher_uses_no_labels_and_is_non_negative():
    model = linear([0.5, -1.0])
    a = fisher(
        model,
        context(model, X, Y).plain_batches(1),
        "model",
        generator=torch.Generator().manual_seed(0),
    )
    b = fisher(
        model,
        context(model, X, Y + 100).plain_batches(1),
        "model",
        generator=torch.Generator().manual_seed(0),
    )
    assert torch.equal(a["weight"], b["weight"]) and (a["weight"] >= 0).all()
    # Each scene's target is out + 2 n (the loss's likelihood has variance 4), its gradient
    # 2 (out - (out + 2 n)) (x, 1) = -4 n (x, 1): the same draws in the same order give
    # (4 n x)^2 averaged.
    noise = torch.randn((2, 1), generator=torch.Generator().manual_seed(0))
    expected = (16 * noise**2 * X**2).mean(dim=0)
    assert a["weight"].flatten().tolist() == pytest.approx(expected.tolist(), rel=1e-5)
    # batch_model, before issue 48: N(0, 1) targets, one draw per batch (here of one scene)
    old = fisher(
        model,
        context(model, X, Y).plain_batches(1),
        "batch_model",
        generator=torch.Generator().manual_seed(0),
    )
    expected = (4 * noise**2 * X**2).mean(dim=0)
    assert old["weight"].flatten().tolist() == pytest.approx(expected.tolist(), rel=1e-5)
    assert EWC(lam=2.0, kind="batch_model").coefficient == 2.0  # no 1/2, as then


def test_per_scene_fisher_of_the_scholar_equals_one_backward_per_scene():
    """vmap's per-scene gradients through BatchNorm (eval mode) and both the root and the top:
    the same as a loop of one backward per scene (float32 sums of ~100 products: 1e-5)."""
    torch.manual_seed(0)
    model = Scholar(MLPRoot(in_dim=5, hidden=(8,)), Top(8, hidden=4))
    x, y = torch.randn(6, 5), torch.randn(6, 8) + 3
    model.train()
    model(x)  # running statistics that are not the defaults
    f = fisher(model, context(model, x, y, batch_size=4).plain_batches())
    model.eval()
    loop = {n: torch.zeros_like(p) for n, p in model.named_parameters()}
    for i in range(6):
        model.zero_grad()
        nn.functional.mse_loss(model(x[i : i + 1]), y[i : i + 1]).backward()
        for n, p in model.named_parameters():
            loop[n] += p.grad**2 / 6
    assert model.training is False  # fisher() left the mode as it found it
    for n in loop:
        assert torch.allclose(f[n], loop[n], rtol=1e-5, atol=1e-9), n


def test_ewc_penalty_carries_the_half_and_one_term_per_task():
    """(lambda / 2) sum F (theta - theta*)^2 (Kirkpatrick et al., eq. 3)."""
    model = linear([0.5, -1.0])
    ewc = EWC(lam=2.0)
    ctx = context(model, X, Y)
    ewc.on_task_end(ctx)
    assert ewc.penalty(model).item() == 0.0  # at the anchor
    with torch.no_grad():
        model.weight += torch.tensor([[0.1, -0.2]])
        model.bias += 0.5
    # 2 / 2 * (45 * 0.1^2 + 22.5 * 0.2^2 + 9 * 0.5^2)
    assert ewc.penalty(model).item() == pytest.approx(0.45 + 0.9 + 2.25)
    batch = EWC(lam=2.0, kind="batch")  # before issue 48: no 1/2
    batch.terms = ewc.terms
    assert batch.penalty(model).item() == pytest.approx(2 * (0.45 + 0.9 + 2.25))
    ewc.on_task_end(ctx)
    assert len(ewc.terms) == 2
    loss = ewc.loss(ctx, None, None, None, torch.tensor(1.0))
    assert loss.item() == pytest.approx(1.0 + ewc.penalty(model).item())


def test_ewc_online_keeps_one_decayed_fisher():
    model = linear([0.5, -1.0])
    online = EWCOnline(lam=1.0, gamma=0.5)
    ctx = context(model, X, Y)
    online.on_task_end(ctx)
    first = online.terms[0][0]["weight"].clone()
    with torch.no_grad():
        model.weight.copy_(torch.tensor([[1.0, 1.0]]))
    second = fisher(model, ctx.plain_batches(1))["weight"]
    online.on_task_end(ctx)
    assert len(online.terms) == 1
    assert torch.allclose(online.terms[0][0]["weight"], 0.5 * first + second)
    assert torch.equal(online.terms[0][1]["weight"], torch.tensor([[1.0, 1.0]]))  # latest anchor
    assert online.coefficient == 0.5  # lambda / 2 (Schwarz et al., eq. 8)


class WithIdle(nn.Module):
    """A linear model plus a parameter that never touches the output."""

    def __init__(self):
        super().__init__()
        self.lin = linear([0.5, -1.0])
        self.idle = nn.Parameter(torch.ones(3))

    def forward(self, x):
        return self.lin(x)


def test_si_importance_only_for_moved_parameters():
    torch.manual_seed(0)
    model = WithIdle()
    optimizer = torch.optim.Adam(model.parameters(), lr=0.1)
    si = SI(c=1.0, xi=0.1)
    ctx = context(model, X, Y, optimizer=optimizer)
    si.on_task_start(ctx)
    for _ in range(20):
        loss = nn.functional.mse_loss(model(X), Y)
        optimizer.zero_grad()
        loss.backward()
        si.before_step(ctx)
        optimizer.step()
        si.after_step(ctx)
    si.on_task_end(ctx)
    importance, anchor = si.terms[0]
    assert torch.equal(importance["idle"], torch.zeros(3))  # never moved: nothing
    assert (importance["lin.weight"] != 0).all()
    assert torch.equal(anchor["lin.weight"], model.lin.weight.detach())
    # A second task adds to the importance.
    si.on_task_start(ctx)
    si.on_task_end(ctx)
    assert torch.allclose(si.terms[0][0]["lin.weight"], importance["lin.weight"])  # no steps: +0


def _si_step(si: SI, ctx: LocalContext, grad: list[float], move: list[float]) -> None:
    """One optimiser step by hand: the gradient the step saw, then the change it made."""
    w, b = ctx.model.weight, ctx.model.bias
    w.grad, b.grad = torch.tensor([[grad[0]]]), torch.tensor([grad[1]])
    si.before_step(ctx)
    with torch.no_grad():
        w += move[0]
        b += move[1]
    si.after_step(ctx)


def _si_task(clamp: str) -> tuple[SI, LocalContext]:
    """Task 1 on the 2-parameter model w x + b from (1, 0), xi = 0.1, c = 2, two steps:
    gradients (1, -2) then (2, 1), changes (-0.5, +0.5) then (+0.6, -0.5) - the second one
    against w's gradient, as a step with momentum can be.
    omega_w = -(1)(-0.5) - (2)(0.6) = -0.7, Delta_w = 0.1: gain -0.7 / (0.01 + 0.1);
    omega_b = -(-2)(0.5) - (1)(-0.5) = 1.5, Delta_b = 0: gain 1.5 / 0.1 = 15."""
    model = linear([1.0])
    si = SI(c=2.0, xi=0.1, clamp=clamp)
    ctx = context(model, X3, Y3)
    si.on_task_start(ctx)
    _si_step(si, ctx, [1.0, -2.0], [-0.5, 0.5])
    _si_step(si, ctx, [2.0, 1.0], [0.6, -0.5])
    si.on_task_end(ctx)
    return si, ctx


def test_si_importance_by_hand_keeps_a_negative_gain_as_published():
    """Zenke et al. 2017, eq. 5: Omega = omega / (Delta^2 + xi), no clamp."""
    si, ctx = _si_task("none")
    importance, anchor = si.terms[0]
    assert si.task_metrics(ctx) == {"negative": 0.5}  # w's of the 2: logged as si/negative
    assert importance["weight"].item() == pytest.approx(-0.7 / 0.11, rel=1e-5)
    assert importance["bias"].item() == pytest.approx(15.0, rel=1e-5)
    assert anchor["weight"].item() == pytest.approx(1.1)


def test_si_clamp_task_is_the_form_before_issue_48_and_total_the_authors_code():
    task, ctx = _si_task("task")
    assert task.terms[0][0]["weight"].item() == 0.0
    assert task.terms[0][0]["bias"].item() == pytest.approx(15.0, rel=1e-5)
    total, _ = _si_task("total")
    assert total.terms[0][0]["weight"].item() == 0.0
    # A second task with gains w: +0.1 / (0 + 0.1) = 1 (gradient -1, change +0.1, then back)
    # and b: -0.2 / 0.1 = -2 (gradient 1, change +0.2, then back). clamp=task clamps each
    # gain (w 0 + 1, b 15 + 0), total the sums (w max(0, 0 + 1), b max(0, 15 - 2)), none
    # neither (w -6.36 + 1, b 13).
    cases = ((task, 1.0, 15.0), (total, 1.0, 13.0), (_si_task("none")[0], 1 - 0.7 / 0.11, 13.0))
    for si, w, b in cases:
        si.coefficient = 0.0  # no penalty gradient to take off in this check
        si.on_task_start(ctx)
        _si_step(si, ctx, [-1.0, 1.0], [0.1, 0.2])
        _si_step(si, ctx, [0.0, 0.0], [-0.1, -0.2])
        si.on_task_end(ctx)
        assert si.terms[0][0]["weight"].item() == pytest.approx(w, rel=1e-5)
        assert si.terms[0][0]["bias"].item() == pytest.approx(b, rel=1e-5)


def test_si_path_integral_follows_the_loss_without_its_own_penalty():
    """As published (the authors' ``unreg_grads``): in task 2 the step's gradient includes
    SI's penalty 2 c Omega (theta - theta*); omega uses the gradient without it."""
    si, ctx = _si_task("none")  # Omega = (-6.3636, 15), anchor (1.1, 0), c = 2
    with torch.no_grad():  # away from the anchor by (0.2, -0.1)
        ctx.model.weight += 0.2
        ctx.model.bias -= 0.1
    si.on_task_start(ctx)  # the task starts here
    # the gradient the step saw: the loss's (1, 1) plus the penalty's 2 x 2 x Omega x offset
    pen = [4 * (-0.7 / 0.11) * 0.2, 4 * 15.0 * -0.1]
    _si_step(si, ctx, [1.0 + pen[0], 1.0 + pen[1]], [-0.1, -0.1])
    assert si.omega["weight"].item() == pytest.approx(0.1, rel=1e-5)  # -(1)(-0.1)
    assert si.omega["bias"].item() == pytest.approx(0.1, rel=1e-5)
    old = SI(c=2.0, xi=0.1, path_gradient="loss+penalty")  # before issue 48
    old.terms = si.terms
    old.on_task_start(ctx)
    _si_step(old, ctx, [1.0 + pen[0], 1.0 + pen[1]], [-0.1, -0.1])
    assert old.omega["bias"].item() == pytest.approx(-(1.0 + pen[1]) * -0.1, rel=1e-5)


def test_mas_importance_is_the_mean_over_scenes_of_each_scenes_gradient():
    """Aljundi et al. 2018, eq. 4: Omega = mean_n |d ||f(x_n)||^2 / d theta| = |2 out_n (x_n,
    1)|: w (1, 4, 1), b (1, 2, 1) on the three scenes, whatever the batch size."""
    model = linear([0.5])
    for batch_size in (1, 2):
        imp = output_norm_importance(model, context(model, X3, Y3, batch_size=batch_size).batches)
        assert imp["weight"].item() == pytest.approx(2.0, rel=1e-6)
        assert imp["bias"].item() == pytest.approx(4 / 3, rel=1e-6)


def test_mas_importance_is_zero_where_the_output_does_not_depend_and_accumulates():
    model = WithIdle()
    imp = output_norm_importance(model, context(model, X, Y).plain_batches(2))
    # ||w.x + b||^2: d/dw = 2 out x; out = -1.5 and 2.5 for the two samples.
    assert imp["lin.weight"].flatten().tolist() == pytest.approx([(3 + 15) / 2, (6 + 5) / 2])
    assert imp["lin.bias"].tolist() == pytest.approx([(3 + 5) / 2])
    assert torch.equal(imp["idle"], torch.zeros(3))
    mas = MAS(lam=1.0)
    ctx = context(model, X, Y)
    mas.on_task_end(ctx)
    mas.on_task_end(ctx)
    assert torch.allclose(mas.terms[0][0]["lin.weight"], 2 * imp["lin.weight"])  # accumulates


def test_mas_batch_importance_is_the_form_before_issue_48():
    """importance=batch: |gradient of each batch's mean ||f||^2|, averaged over batches:
    {1, 2}: ((1 + 4) / 2, (1 + 2) / 2), {3}: (1, 1) -> (1.75, 1.25)."""
    model = linear([0.5])
    ctx = context(model, X3, Y3, batch_size=2)
    imp = output_norm_importance(model, ctx.plain_batches(), kind="batch")
    assert imp["weight"].item() == pytest.approx(1.75, rel=1e-6)
    assert imp["bias"].item() == pytest.approx(1.25, rel=1e-6)


def test_naive_rehearsal_memory_is_bounded_and_holds_only_past_tasks():
    inputs = torch.arange(60, dtype=torch.float32).view(30, 2)
    targets = torch.arange(30, dtype=torch.float32).view(30, 1)
    tasks = [np.arange(0, 10), np.arange(10, 20), np.arange(20, 30)]
    nr = NaiveRehearsal(capacity=8, replay_ratio=0.5, seed=1)
    model = linear([1.0, 0.0])
    assert len(nr.memory) == 0
    x, y = context(model, inputs, targets, tasks[0], task=0, batch_size=4).batches.gather(
        torch.arange(4)
    )
    assert nr.batch(None, x, y)[0].shape[0] == 4  # nothing to rehearse during task 1
    for t, positions in enumerate(tasks):
        ctx = context(model, inputs, targets, positions, task=t, batch_size=4)
        if t > 0:  # during task t: batches get memory samples of earlier tasks only
            xb, yb = ctx.batches.gather(torch.as_tensor(positions[:4]))
            xm, ym = nr.batch(ctx, xb, yb)
            assert xm.shape == (6, 2)
            assert set(ym[4:].flatten().int().tolist()) <= set(np.concatenate(tasks[:t]).tolist())
        nr.on_task_end(ctx)
        memory = nr.memory
        assert len(memory) <= 8 and len(set(memory.tolist())) == len(memory)
        assert set(memory.tolist()) <= set(np.concatenate(tasks[: t + 1]).tolist())
        assert all(len(p) == 8 // (t + 1) for p in nr.by_task.values())  # an equal share each


def test_lwf_distils_the_task_start_outputs_by_hand():
    """Li & Hoiem 2016 for regression: nothing in task 1; from task 2, loss + alpha * MSE of
    the outputs to those of the model as it was when the task started."""
    model = linear([0.5, -1.0])
    lwf = LwF(alpha=3.0)
    lwf.on_task_start(context(model, X, Y, task=0))
    assert lwf.previous is None
    assert lwf.loss(None, X, Y, model(X), torch.tensor(1.0)).item() == 1.0
    lwf.on_task_start(context(model, X, Y, task=1))  # task 2 starts: f_start(X) = (-1.5, 4)
    with torch.no_grad():
        model.weight += torch.tensor([[1.0, 0.0]])  # f(X) = (-0.5, 7): differences (1, 3)
    ctx = context(model, X, Y, task=1)
    loss = lwf.loss(ctx, X, Y, model(X), torch.tensor(1.0))
    assert loss.item() == pytest.approx(1.0 + 3.0 * (1 + 9) / 2)
    loss.backward()  # the gradient flows into the model, not into the frozen copy
    assert model.weight.grad is not None
    assert all(p.grad is None and not p.requires_grad for p in lwf.previous.parameters())
    # A checkpoint mid-task restores the copy: the same loss after a resume.
    resumed = LwF(alpha=3.0)
    resumed.load_state_dict(lwf.state_dict())
    resumed.on_round_start(context(linear([9.0, 9.0]), X, Y, task=1))
    again = resumed.loss(ctx, X, Y, model(X), torch.tensor(1.0))
    assert again.item() == pytest.approx(loss.item())
    config = load_config(None, ["method=FedRoot-LwF", "continual.lwf.alpha=0.25"])
    (plugin,) = continual_plugins(config.continual, 0, 0)
    assert isinstance(plugin, LwF) and plugin.alpha == 0.25


def test_vae_loss_decreases_on_a_fixed_latent_set():
    torch.manual_seed(0)
    # Low-rank ReLU features, like a root's: 4 factors spread over 32 dimensions.
    latents = torch.relu(torch.randn(256, 4) @ torch.randn(4, 32))
    vae = LatentVAE(32, hidden=64, latent=8, lr=1e-3)
    report = vae.fit(latents, epochs=40, batch_size=32, generator=torch.Generator().manual_seed(0))
    # No held-out latents: every epoch runs and the last one's weights are kept.
    assert report.epochs == 40 and report.best_epoch == 40 and report.heldout == []
    assert report.train[-1] < 0.6 * report.train[0]
    assert not vae.training  # fit leaves the generator in eval mode
    samples = vae.sample(100, torch.Generator().manual_seed(1))
    assert samples.shape == (100, 32)
    assert torch.allclose(samples.mean(0), latents.mean(0), atol=0.6 * latents.std(0).max())


def tiny_scholar() -> Scholar:
    torch.manual_seed(0)
    root = MLPRoot(in_dim=4, hidden=(6,))
    return Scholar(root, Top(root.out_dim, hidden=5))


def lgr_client(model, inputs, targets, lgr, batch_size=5) -> Client:
    """One client whose task "a" is scenes 0-9 and task "b" scenes 10-19."""
    data = {
        name: SceneBatches(inputs, targets, positions, batch_size, shuffle=False)
        for name, positions in (("a", np.arange(10)), ("b", np.arange(10, 20)))
    }
    return Client(0, model, model.configure_optimizers(), data, [lgr])


def test_fedlgr_pseudo_labels_come_from_the_pre_update_top():
    model = tiny_scholar()
    inputs, targets = torch.randn(20, 4), torch.rand(20, 8) * 4 + 1
    lgr = LatentReplay(hidden=16, latent=3, epochs=5, batch_size=8, lr=1e-3, lr_root=1e-5, seed=3)
    client = lgr_client(model, inputs, targets, lgr)
    optimizer = client.optimizer
    ctx1 = lgr_context(client, 0)
    lgr.on_task_start(ctx1)
    assert lgr.labeller is None  # nothing to replay in task 1
    train_locally(client, ctx1, epochs=1)
    lr = {g["name"]: g["lr"] for g in optimizer.param_groups}
    assert lr == {"root": 1e-3, "top": 1e-3}  # task 1: lr_R not applied yet
    assert lgr.generator is None and lgr.forward(ctx1, *next(ctx1.batches.peek())) is None
    lgr.on_task_end(ctx1)  # the generator learns task 1's latents (5 epochs at most)
    assert lgr.generator is not None and lgr.tasks_learnt == 1
    assert 1 <= lgr.fit_report.epochs <= 5 and len(lgr.history) == lgr.fit_report.epochs

    ctx2 = lgr_context(client, 1)
    before = {k: v.clone() for k, v in model.top.state_dict().items()}
    lgr.on_task_start(ctx2)  # the labeller: a frozen copy of the top as the task begins
    assert not lgr.labeller.training
    assert all(not p.requires_grad for p in lgr.labeller.parameters())
    for _ in range(2):  # two rounds of task 2: the top moves, the labeller does not
        train_locally(client, ctx2, epochs=1)
        lr = {g["name"]: g["lr"] for g in optimizer.param_groups}
        assert lr == {"root": 1e-5, "top": 1e-3}  # lr_R << lr_T from task 2 on
    assert not torch.equal(model.top.state_dict()["net.1.weight"], before["net.1.weight"])
    latents, labels = lgr.pseudo_samples(7)
    assert latents.shape == (7, model.root.out_dim) and labels.shape == (7, 8)
    frozen = Top(model.root.out_dim, hidden=5).eval()
    frozen.load_state_dict(before)
    with torch.no_grad():
        assert torch.allclose(labels, frozen(latents))  # the top as it was when the task began
        assert not torch.allclose(labels, model.top.eval()(latents))
    lgr.on_task_end(ctx2)
    assert lgr.labeller is None and lgr.tasks_learnt == 2


def test_fedlgr_joint_forward_puts_real_and_pseudo_latents_in_one_loss():
    model = tiny_scholar()
    inputs, targets = torch.randn(20, 4), torch.rand(20, 8) * 4 + 1
    lgr = LatentReplay(
        schedule="joint", hidden=16, latent=3, epochs=2, batch_size=8, replay_ratio=0.5, seed=3
    )
    client = lgr_client(model, inputs, targets, lgr, batch_size=4)
    ctx1 = lgr_context(client, 0)
    x, y = client.batches.gather(torch.arange(4))
    assert lgr.forward(ctx1, x, y) is None  # no generator yet: the model's own outputs
    assert lgr.epochs(ctx1, 3) is None  # train.epochs
    lgr.on_task_end(ctx1)
    ctx2 = lgr_context(client, 1)
    lgr.on_task_start(ctx2)
    assert lgr.epochs(ctx2, 3) is None  # joint: train.epochs, root and top together
    x, y = client.batches.gather(torch.arange(10, 14))
    state = lgr.generator_rng.get_state()
    latents, labels = lgr.pseudo_samples(2)  # replay_ratio 0.5 x 4 real samples
    lgr.generator_rng.set_state(state)
    model.train()
    outputs, union = lgr.forward(ctx2, x, y)
    with torch.no_grad():
        expected = model.top(torch.cat([model.root(x), latents]))
    assert torch.allclose(outputs, expected, atol=1e-6)
    assert torch.equal(union, torch.cat([y, labels]))
    real = nn.functional.mse_loss(outputs[:4], y).item()
    replay = nn.functional.mse_loss(outputs[4:], labels).item()
    assert nn.functional.mse_loss(outputs, union).item() == pytest.approx(
        (real * 4 + replay * 2) / 6, rel=1e-5
    )


@pytest.mark.slow
def test_the_ewc_benchmark_prints_its_three_tables(tmp_path):
    """``bench/ewc.py --quick`` (~30 s): the cost of both importance forms, the batch form's
    ratio to the per-scene one (below 1 for EWC: a batch's mean gradient squared is at most
    the mean of its squares), and a forgetting row per run."""
    done = subprocess.run(
        [sys.executable, str(REPO / "bench" / "ewc.py"), "--quick"],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    lines = done.stdout.splitlines()
    costs = [line.split() for line in lines if line.startswith("MobileNetV2")]
    assert len(costs) == 2 and all(float(c[-1]) > 0 for c in costs), costs
    ewc = next(line.split() for line in lines if line.startswith("EWC Fisher "))
    median, low, high = (float(v) for v in ewc[3:6])
    assert 0 < low <= median <= high <= 1, ewc
    runs = [line for line in lines if line.startswith(("FedRoot-FT ", "FedRoot-EWC "))]
    assert len(runs) == 2 * 3, runs  # FT, EWC per scene, EWC batch; per run and their means
