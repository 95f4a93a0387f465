"""FedLGR on tiny clients with hand-checkable numbers (an MLP root over 4 inputs, two
tasks of random scenes), and FedLGR's fast config."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from fedlgr.core.client.plugins import LocalContext
from fedlgr.core.client.training import Client, train_locally
from fedlgr.core.continual.lgr import LatentReplay
from fedlgr.core.data.augment import SceneBatches
from fedlgr.core.models.scholar import MLPRoot, Scholar, Top

from .runs import fast_config

BN_BUFFERS = ("running_mean", "running_var", "num_batches_tracked")


def tiny_scholar() -> Scholar:
    torch.manual_seed(0)
    root = MLPRoot(in_dim=4, hidden=(6,))
    return Scholar(root, Top(root.out_dim, hidden=5))


def make_client(lgr: LatentReplay, batch_size: int = 6, n: int = 12, **plugins) -> Client:
    """Task "a": scenes 0..n-1, task "b": scenes n..2n-1, over random inputs (in order)."""
    model = tiny_scholar()
    torch.manual_seed(1)
    inputs, targets = torch.randn(2 * n, 4), torch.rand(2 * n, 8) * 4 + 1
    data = {
        name: SceneBatches(inputs, targets, positions, batch_size, shuffle=False)
        for name, positions in (("a", np.arange(n)), ("b", np.arange(n, 2 * n)))
    }
    extra = list(plugins.values())
    return Client(0, model, model.configure_optimizers(), data, [lgr, *extra])


def context(client: Client, task: int, epochs: int = 1) -> LocalContext:
    client.task = "ab"[task]
    return LocalContext(
        0,
        task + 1,
        client.model,
        {},
        torch.device("cpu"),
        task=task,
        epochs=epochs,
        task_name=client.task,
        batches=client.batches,
        optimizer=client.optimizer,
        seen=[client.data[t] for t in "ab"[: task + 1]],
    )


def after_task_one(lgr: LatentReplay, **kwargs) -> tuple[Client, LocalContext]:
    """A client that trained task "a" for one round and ended it; the context of "b"."""
    client = make_client(lgr, **kwargs)
    ctx = context(client, 0)
    lgr.on_task_start(ctx)
    train_locally(client, ctx, 1)
    lgr.on_task_end(ctx)
    assert lgr.replaying
    ctx = context(client, 1)
    lgr.on_task_start(ctx)
    return client, ctx


def small_lgr(**kwargs) -> LatentReplay:
    settings = dict(hidden=16, latent=3, epochs=5, batch_size=8, lr=1e-3, seed=3)
    return LatentReplay(**(settings | kwargs))


def state(module: nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def fedlgr_config(synth_dir, cache_dir, store, *overrides):
    return fast_config(
        synth_dir,
        cache_dir,
        store,
        "method=FedLGR",
        "data.modality=features",
        "continual.rounds_per_task=1",
        "continual.lgr.epochs=3",
        "runtime.threads=1",
        *overrides,
    )
