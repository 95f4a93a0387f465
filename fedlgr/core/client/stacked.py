"""Several clients' local training as one stacked model (``runtime.concurrency=batched``).

The paper trains several clients in parallel on one GPU. A client's model (a narrow
MobileNetV2 root and a small top, batches of 16) leaves most of a GPU idle, so
:func:`train_batched` trains K clients in lockstep as one model: at each step it stacks
the clients' parameters and buffers along a new leading dimension and runs one forward
with :func:`torch.func.functional_call` under :func:`torch.func.vmap` over that dimension
(the clients' batches stacked as [K, B, ...]); convolutions and matrix products then run
as K-wide grouped kernels instead of K small ones.

Every client stays its own, and ends as if trained alone by :func:`train_locally`:

* Gradients: each stacked tensor is ``torch.stack`` of the clients' own leaf parameters,
  and the backward pass goes through the SUM of the per-client losses, whose derivative
  with respect to client k's parameters is client k's loss's alone; autograd routes it
  through the stack into each client's own ``.grad``. Each client's own optimiser then
  zeroes (before the backward pass, as in ``train_locally``) and steps.
* BatchNorm: in training mode BatchNorm updates its running statistics in place. The
  clients' buffers (``running_mean``, ``running_var``, ``num_batches_tracked``) are passed
  stacked too, so vmap's batch-norm rule updates each client's slice with its own batch's
  statistics (torch.func's "Patching Batch Norm" page is about the other case, a single
  unbatched buffer, which vmap cannot update; its remedy, dropping running statistics
  with ``replace_all_batch_norm_modules_``, would change the model). The updated slices
  are copied back into each client's buffers after the step.
* Data: each client's batches come from its own ``client.batches`` iterator, one epoch at
  a time, drawn exactly as ``train_locally`` draws them (the batch past ``max_batches`` is
  drawn too before the epoch stops, so the client's generator ends in the same state).
  At each step the clients that still have a batch are grouped by batch shape: a group of
  two or more trains stacked, a client alone trains a plain step. Clients run out of
  batches independently (ragged shards, a smaller last batch), and a batch of fewer than
  two samples is skipped as in ``train_locally`` (BatchNorm cannot train on it).

Only clients without plugins are supported (FedAvg, FedRootAvg, FedBN, FedOpt and the
FedRoot variants without a continual-learning method): plugin hooks act on one client's
loop, so a client with plugins is refused with an error that names the setting.
(What has been measured, and on which devices: docs/runtimes.md.)
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Callable

import torch
from torch import nn
from torch.func import functional_call, vmap

from fedlgr.core.client.plugins import LocalContext
from fedlgr.core.client.training import Client, LocalStats, round_stats
from fedlgr.errors import FedlgrError


def train_batched(
    clients: list[Client],
    ctxs: list[LocalContext],
    epochs: int,
    max_batches: int | None = None,
    channels_last: bool = False,
    autocast=contextlib.nullcontext,
    on_epoch: Callable[[int], object] | None = None,
) -> list[LocalStats]:
    """``train_locally`` for every client of ``clients`` (with ``ctxs[k]`` the context of
    ``clients[k]``), stacked into one model where their batches have the same shape.

    The clients move through the epochs together, so ``on_epoch(epoch)`` is called once
    per finished epoch for all of them (not once per client). Returns each client's
    :class:`LocalStats`, computed as ``train_locally`` computes them.
    """
    if len(clients) != len(ctxs):
        raise ValueError(f"{len(clients)} clients but {len(ctxs)} contexts")
    refuse_plugins(clients)
    stacks = [_Stackable(client) for client in clients]
    templates: dict[tuple, nn.Module] = {}  # architecture -> a parameterless copy
    for s in stacks:
        s.client.model.train()
        if s.signature not in templates:
            templates[s.signature] = copy.deepcopy(s.client.model).to("meta").train()
    totals = [torch.zeros((), device=ctx.device) for ctx in ctxs]
    seen = [0] * len(clients)
    for epoch in range(epochs):
        epoch_batches = [enumerate(client.batches) for client in clients]
        active = list(range(len(clients)))
        while active:
            groups, active = _next_batches(
                epoch_batches, active, stacks, max_batches, channels_last
            )
            for key, group in groups.items():
                grouped = [stacks[k] for k, _, _ in group]
                xs = [x for _, x, _ in group]
                ys = [y for _, _, y in group]
                if len(group) == 1:
                    losses = [_plain_step(grouped[0].client, xs[0], ys[0], autocast)]
                else:
                    losses = _batched_step(templates[key[0]], grouped, xs, ys, autocast)
                for (k, x, _), loss in zip(group, losses, strict=True):
                    totals[k] += loss * len(x)
                    seen[k] += len(x)
        if on_epoch is not None:
            on_epoch(epoch + 1)
    return [
        round_stats(client, ctx, total, n)
        for client, ctx, total, n in zip(clients, ctxs, totals, seen, strict=True)
    ]


Group = list[tuple[int, torch.Tensor, torch.Tensor]]  # (client's position, x, y)


def _next_batches(
    epoch_batches: list, active: list[int], stacks: list, max_batches, channels_last: bool
) -> tuple[dict[tuple, Group], list[int]]:
    """The next batch of each of the ``active`` clients, grouped by what can be stacked
    (architecture, shapes, dtypes, device); the clients whose epoch goes on."""
    groups: dict[tuple, Group] = {}
    still = []
    for k in active:
        step, batch = next(epoch_batches[k], (None, None))
        if batch is None or (max_batches is not None and step >= max_batches):
            continue  # the client's epoch is over
        still.append(k)
        x, y = batch
        if len(x) < 2:  # BatchNorm cannot train on a single sample
            continue
        if channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        key = (stacks[k].signature, x.shape, x.dtype, x.device, y.shape, y.dtype)
        groups.setdefault(key, []).append((k, x, y))
    return groups, still


def refuse_plugins(clients: list[Client]) -> None:
    """Raise if any client has plugins: their hooks act on one client's own loop."""
    with_plugins = [
        f"client {c.index} ({', '.join(p.name for p in c.plugins)})" for c in clients if c.plugins
    ]
    if with_plugins:
        raise FedlgrError(
            "runtime.concurrency=batched trains clients without plugins only (FedAvg, "
            "FedRootAvg, FedBN, FedOpt and the FedRoot variants without a continual-learning "
            f"method); {'; '.join(with_plugins)} have plugins from the method: use "
            "runtime.concurrency=threads or sequential"
        )


class _Stackable:
    """A client's parameters and buffers by name, and its architecture's signature."""

    def __init__(self, client: Client):
        self.client = client
        model = client.model
        self.params = dict(model.named_parameters())
        self.buffers = dict(model.named_buffers())
        # Clients stack only with clients of the same architecture: module types in
        # order, then every tensor's name, shape and dtype.
        self.signature = (
            tuple(type(m).__name__ for m in model.modules()),
            tuple((n, tuple(t.shape), t.dtype) for n, t in self.params.items()),
            tuple((n, tuple(t.shape), t.dtype) for n, t in self.buffers.items()),
        )


def _plain_step(client: Client, x: torch.Tensor, y: torch.Tensor, autocast) -> torch.Tensor:
    """One step of ``train_locally`` without plugins; returns the task loss (detached)."""
    with autocast():
        loss = nn.functional.mse_loss(client.model(x).float(), y)
    client.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    client.optimizer.step()
    return loss.detach()


def _batched_step(
    template: nn.Module,
    stacks: list[_Stackable],
    xs: list[torch.Tensor],
    ys: list[torch.Tensor],
    autocast,
) -> torch.Tensor:
    """One step of every client of ``stacks`` on its own batch, as one vmapped forward and
    one backward; returns the clients' task losses (detached)."""
    first = stacks[0]
    params = {n: torch.stack([m.params[n] for m in stacks]) for n in first.params}
    buffers = {n: torch.stack([m.buffers[n] for m in stacks]) for n in first.buffers}
    y = torch.stack(ys)

    def forward(p: dict, b: dict, x: torch.Tensor) -> torch.Tensor:
        return functional_call(template, (p, b), (x,))

    with autocast():
        outputs = vmap(forward)(params, buffers, torch.stack(xs))
        losses = torch.stack(
            [nn.functional.mse_loss(outputs[k].float(), y[k]) for k in range(len(stacks))]
        )
    for m in stacks:
        m.client.optimizer.zero_grad(set_to_none=True)
    losses.sum().backward()  # d(sum)/d(client k's parameters) = d(loss k)/d(them)
    for m in stacks:
        m.client.optimizer.step()
    with torch.no_grad():  # the running statistics the forward pass updated in the stack
        for n, stacked in buffers.items():
            for k, m in enumerate(stacks):
                m.buffers[n].copy_(stacked[k])
    return losses.detach()
