"""Every client evaluates its own model on the shared test set (SPEC 5); the server scores
the global model on the same scenes (``federated.server_eval``)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from fedlgr.core.data.augment import normalize
from fedlgr.core.schedule import ALL


def scored_clients(config) -> Callable[[list[int]], tuple[int, ...] | None]:
    """``federated.evaluate``: which clients score the new global tensors in a round, given
    the round's chosen clients: all of them (None), the chosen ones, or a sample of
    ``federated.eval_clients`` drawn once from the run's seed (the same every round)."""
    federated, clients = config.federated, config.data.clients
    if federated.evaluate == "chosen":
        return tuple
    if federated.evaluate == "sample":
        rng = np.random.default_rng([config.seed, 0xE7A1])
        n = min(federated.eval_clients, clients)
        sample = tuple(sorted(int(c) for c in rng.choice(clients, size=n, replace=False)))
        return lambda chosen: sample
    return lambda chosen: None


@dataclass
class EvalSet:
    """The shared test scenes, ready for a model: inputs (normalised images or
    descriptors, on the device), targets, each task's rows (``test_rows``) and, per task,
    the rows of every task seen up to it (``seen_rows``)."""

    test_inputs: torch.Tensor
    test_targets: torch.Tensor
    test_rows: dict[str, torch.Tensor]
    seen_rows: list[torch.Tensor]
    autocast: Callable = contextlib.nullcontext


def eval_set(
    scenes, split, tasks: list[str], device, channels_last: bool, autocast=contextlib.nullcontext
) -> EvalSet:
    """The test scenes of ``split`` (tasks: ``["all"]`` in plain FL)."""
    test = split.test
    inputs = scenes.inputs[torch.as_tensor(test)]
    if scenes.images is not None:
        inputs = normalize(inputs)
        if channels_last:
            inputs = inputs.contiguous(memory_format=torch.channels_last)
    targets = scenes.targets[torch.as_tensor(test)]
    where = {t: np.searchsorted(test, split.test_tasks[t]) for t in tasks if t != ALL}
    seen = [
        torch.as_tensor(np.sort(np.concatenate([where[t] for t in tasks[: k + 1]])))
        if tasks != [ALL]
        else torch.arange(len(test))
        for k in range(len(tasks))
    ]
    rows = {t: torch.as_tensor(r) for t, r in where.items()}
    return EvalSet(inputs.to(device), targets, rows, seen, autocast)


def _serial(fn, items):
    return [fn(item) for item in items]


@contextlib.contextmanager
def _eval_mode(modules: list[nn.Module]):
    was_training = [m.training for m in modules]
    for m in modules:
        m.eval()
    try:
        yield
    finally:
        for m, training in zip(modules, was_training, strict=True):
            m.train(training)


def predict(
    model: nn.Module,
    inputs: torch.Tensor,
    batch_size: int,
    autocast=contextlib.nullcontext,
    map=_serial,
) -> torch.Tensor:
    """Model outputs (N, 8) for prepared (normalised, on-device) inputs, in eval mode.
    ``map``: how the batches are spread (a ``ClientPool``'s, to use every worker)."""

    @torch.no_grad()  # no_grad and autocast hold per thread: entered where the work runs
    def batch(x: torch.Tensor) -> torch.Tensor:
        with autocast():
            return model(x).float()

    with _eval_mode([model]):
        return torch.cat(map(batch, _split(inputs, batch_size)))


def predict_tops(
    root: nn.Module,
    tops: list[nn.Module],
    inputs: torch.Tensor,
    batch_size: int,
    autocast=contextlib.nullcontext,
    map=_serial,
) -> list[torch.Tensor]:
    """``predict`` of models ``top_i(root(x))`` that share ``root``: the root's pass once
    per batch, then every top on it (the same batches, hence the same numbers as
    ``predict`` of each whole model)."""

    @torch.no_grad()
    def batch(x: torch.Tensor) -> list[torch.Tensor]:
        with autocast():
            latents = root(x)
            return [top(latents).float() for top in tops]

    with _eval_mode([root, *tops]):
        outputs = map(batch, _split(inputs, batch_size))
    return [torch.cat(per_top) for per_top in zip(*outputs, strict=True)]


def _split(inputs: torch.Tensor, batch_size: int) -> list[torch.Tensor]:
    return [inputs[i : i + batch_size] for i in range(0, len(inputs), batch_size)]
