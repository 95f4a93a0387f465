"""Loss scaling for train.precision=16-mixed (float16 autocast on a GPU): the scaled
backward, the unscaled gradients the plugins see, the skipped step. The CUDA scaler's
logic is the CPU scaler's (``torch.amp.GradScaler("cpu")``), which runs here."""

from __future__ import annotations

import copy

import pytest
import torch

from fedlgr.core.client.side import ClientSide
from fedlgr.core.client.training import train_locally
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.splits import make_split
from tests.support.runs import fast_config


def client_side(synth_dir, cache_dir, *overrides) -> ClientSide:
    config = fast_config(synth_dir, cache_dir, "sqlite://", "runtime.threads=1", *overrides)
    scenes = load_scenes(config.data)
    split = make_split(scenes.table, config.data)
    return ClientSide(config, scenes, split, [0], torch.device("cpu"))


def test_16_mixed_on_cpu_needs_no_scaler(synth_dir, cache_dir):
    """Fabric runs 16-mixed as bfloat16 autocast on CPU: float32's exponent range."""
    side = client_side(synth_dir, cache_dir, "train.precision=16-mixed")
    assert side.clients[0].scaler is None
    assert side.context(side.clients[0], 1, 0).scaler is None


def test_a_scaled_step_is_the_unscaled_step_and_plugins_see_true_gradients(synth_dir, cache_dir):
    """A power-of-two scale is exact in float32: with the scaler the weights, the Adam
    state and SI's importance (read from the gradients in ``before_step``) are bit for bit
    those without - unless the gradients reached the plugins or the step still scaled."""
    side = client_side(synth_dir, cache_dir, "method=FedAvg-SI", "train.max_batches=null")
    plain = side.clients[0]
    scaled = copy.deepcopy(plain)
    scaled.scaler = torch.amp.GradScaler("cpu", init_scale=2.0**12, growth_interval=1)
    for client in (plain, scaled):
        ctx = side.context(client, 1, 0)
        for plugin in client.plugins:
            plugin.on_task_start(ctx)
        train_locally(client, ctx, epochs=2)
    assert scaled.scaler.get_scale() > 2.0**12  # every step was finite: the scale grew
    scaled_state = scaled.model.state_dict()
    for name, a in plain.model.state_dict().items():
        b = scaled_state[name]
        assert torch.equal(a, b), name
    si_plain, si_scaled = plain.plugins[0], scaled.plugins[0]
    assert si_plain.name == "si" and si_plain.omega.keys() == si_scaled.omega.keys()
    assert any(v.abs().sum() > 0 for v in si_plain.omega.values())
    for name in si_plain.omega:
        assert torch.equal(si_plain.omega[name], si_scaled.omega[name]), name


def test_a_step_with_an_infinite_gradient_is_skipped_and_the_scale_halved(synth_dir, cache_dir):
    side = client_side(synth_dir, cache_dir)
    client = side.clients[0]
    client.scaler = torch.amp.GradScaler("cpu", init_scale=2.0**12)
    before = copy.deepcopy(client.model.state_dict())
    ctx = side.context(client, 1, 0)
    # A loss that overflows once scaled: 3e38 x 4096 is inf in float32.
    params = [p for p in client.model.parameters() if p.requires_grad]
    loss = params[0].sum() * 0 + params[0].flatten()[0] * 3e38
    from fedlgr.core.client.training import backward, optimizer_step

    client.optimizer.zero_grad(set_to_none=True)
    backward(loss, client.scaler, client.optimizer)
    optimizer_step(client.optimizer, client.scaler)
    assert client.scaler.get_scale() == pytest.approx(2.0**11)
    for key, value in client.model.state_dict().items():
        assert torch.equal(value, before[key]), key
    assert ctx.scaler is client.scaler
