"""Every client evaluates its own model on the shared test set (docs/methods.md); the
server scores the global model on the same scenes (``federated.server_eval``)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from fedlgr.core.data.augment import normalize
from fedlgr.core.messages import RoundPlan
from fedlgr.core.meters.scores import compat_order
from fedlgr.core.schedule import ALL, schedule


def scored_clients(config) -> Callable[[RoundPlan, list[int]], tuple[int, ...] | None]:
    """``federated.evaluate`` and ``federated.eval_every``: which clients score the new
    global tensors in a round, given its plan and its chosen clients: all of them (None),
    the chosen ones, or a sample of ``federated.eval_clients`` drawn once from the run's
    seed (the same every round); none (``()``) in a round off ``eval_every``'s beat, unless
    it ends a task or the run."""
    federated, clients = config.federated, config.data.clients
    every = federated.eval_every
    last = len(schedule(config)) if every > 1 else 1  # the schedule: DP's target may cut it
    if federated.evaluate == "chosen":
        who = tuple
    elif federated.evaluate == "sample":
        rng = np.random.default_rng([config.seed, 0xE7A1])
        n = min(federated.eval_clients, clients)
        sample = tuple(sorted(int(c) for c in rng.choice(clients, size=n, replace=False)))
        who = lambda chosen: sample  # noqa: E731
    else:
        who = lambda chosen: None  # noqa: E731

    def scored(plan: RoundPlan, chosen: list[int]) -> tuple[int, ...] | None:
        if plan.round % every and not plan.last_of_task and plan.round != last:
            return ()
        return who(chosen)

    return scored


@dataclass(frozen=True)
class EvalInputs:
    """The test scenes' inputs as stored (on the device), made ready for a model a batch
    at a time: images stay uint8 - a quarter of float32's bytes, 0.5 GB less for 2,500
    scenes at 128 px - and are normalised (and made channels-last) per batch, with the
    same numbers as normalising them all at once (elementwise); descriptors are used as
    they are."""

    raw: torch.Tensor
    images: bool = False
    channels_last: bool = False

    def __len__(self) -> int:
        return len(self.raw)

    def batch(self, start: int, stop: int) -> torch.Tensor:
        """Rows ``start:stop``, ready for a model."""
        x = self.raw[start:stop]
        if not self.images:
            return x
        x = normalize(x)
        return x.contiguous(memory_format=torch.channels_last) if self.channels_last else x

    def whole(self) -> torch.Tensor:
        """Every row, ready for a model (a copy: for a check, not for a run)."""
        return self.batch(0, len(self))

    @property
    def device(self) -> torch.device:
        return self.raw.device


@dataclass
class EvalSet:
    """The shared test scenes, ready for a model: inputs (:class:`EvalInputs`), targets,
    each task's rows (``test_rows``) and, per task, the rows of every task seen up to it
    (``seen_rows``)."""

    test_inputs: EvalInputs
    test_targets: torch.Tensor
    test_rows: dict[str, torch.Tensor]
    seen_rows: list[torch.Tensor]
    autocast: Callable = contextlib.nullcontext
    # The same rows in the order the LEAP-HRI'24 code scores them (compat_order)
    compat_rows: dict[str, torch.Tensor] = field(default_factory=dict)
    compat_seen: list[torch.Tensor] = field(default_factory=list)

    def rows(self, task: int, compat: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The rows scored after task ``task`` (every task seen so far) and each task's
        rows; ``compat`` (``train.compat_batch_metrics``): in the LEAP-HRI'24 code's order."""
        if compat:
            return self.compat_seen[task], self.compat_rows
        return self.seen_rows[task], self.test_rows


def eval_set(
    scenes, split, tasks: list[str], device, channels_last: bool, autocast=contextlib.nullcontext
) -> EvalSet:
    """The test scenes of ``split`` (tasks: ``["all"]`` in plain FL)."""
    test = split.test
    raw = scenes.inputs[torch.as_tensor(test)].to(device)
    inputs = EvalInputs(raw, scenes.images is not None, channels_last)
    targets = scenes.targets[torch.as_tensor(test)]
    where = {t: np.searchsorted(test, split.test_tasks[t]) for t in tasks if t != ALL}
    seen = [
        torch.as_tensor(np.sort(np.concatenate([where[t] for t in tasks[: k + 1]])))
        if tasks != [ALL]
        else torch.arange(len(test))
        for k in range(len(tasks))
    ]
    rows = {t: torch.as_tensor(r) for t, r in where.items()}
    # each task's rows shuffled, the tasks seen so far one after another
    compat = {t: compat_order(r, k) for k, (t, r) in enumerate(rows.items())}
    compat_seen = [
        torch.cat([compat[t] for t in tasks[: k + 1]])
        if tasks != [ALL]
        else compat_order(torch.arange(len(test)), 0)
        for k in range(len(tasks))
    ]
    return EvalSet(inputs, targets, rows, seen, autocast, compat, compat_seen)


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
    inputs: EvalInputs | torch.Tensor,
    batch_size: int,
    autocast=contextlib.nullcontext,
    map=_serial,
) -> torch.Tensor:
    """Model outputs (N, 8) for ``inputs`` (:class:`EvalInputs`, or a tensor ready for
    the model), in eval mode. ``map``: how the batches are spread (a ``ClientPool``'s, to
    use every worker; each worker prepares its own batches)."""

    @torch.no_grad()  # no_grad and autocast hold per thread: entered where the work runs
    def batch(rows: tuple[int, int]) -> torch.Tensor:
        x = _rows(inputs, *rows)
        with autocast():
            return model(x).float()

    with _eval_mode([model]):
        return torch.cat(map(batch, _split(inputs, batch_size)))


def predict_tops(
    root: nn.Module,
    tops: list[nn.Module],
    inputs: EvalInputs | torch.Tensor,
    batch_size: int,
    autocast=contextlib.nullcontext,
    map=_serial,
) -> list[torch.Tensor]:
    """``predict`` of models ``top_i(root(x))`` that share ``root``: the root's pass once
    per batch, then every top on it (the same batches, hence the same numbers as
    ``predict`` of each whole model)."""

    @torch.no_grad()
    def batch(rows: tuple[int, int]) -> list[torch.Tensor]:
        x = _rows(inputs, *rows)
        with autocast():
            latents = root(x)
            return [top(latents).float() for top in tops]

    with _eval_mode([root, *tops]):
        outputs = map(batch, _split(inputs, batch_size))
    return [torch.cat(per_top) for per_top in zip(*outputs, strict=True)]


def _split(inputs: EvalInputs | torch.Tensor, batch_size: int) -> list[tuple[int, int]]:
    n = len(inputs)
    return [(i, min(i + batch_size, n)) for i in range(0, n, batch_size)]


def _rows(inputs: EvalInputs | torch.Tensor, start: int, stop: int) -> torch.Tensor:
    return inputs.batch(start, stop) if isinstance(inputs, EvalInputs) else inputs[start:stop]
