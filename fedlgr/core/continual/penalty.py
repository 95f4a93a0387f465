"""Quadratic parameter penalties, the common form of EWC, EWC-Online, SI and MAS.

``penalty = coefficient * sum over terms, over parameters: importance * (theta - anchor)^2``

Each method differs only in how it computes the importance and the anchor at the end of a
task (and SI in what it records during training); the penalty is added to the client's
loss before ``backward``. Importance and anchors are per client and never leave it.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable

import torch
from torch import nn
from torch.func import functional_call, grad, vmap

from fedlgr.core.client.plugins import ClientPlugin
from fedlgr.core.continual.batchnorm import eval_mode

Tensors = dict[str, torch.Tensor]


class QuadraticPenalty(ClientPlugin):
    """Holds ``(importance, anchor)`` terms; subclasses fill them in ``on_task_end``.
    ``coefficient`` multiplies the sum: EWC's ``lambda / 2`` (Kirkpatrick et al., eq. 3),
    MAS's ``lambda`` and SI's ``c``."""

    def __init__(self, coefficient: float):
        self.coefficient = coefficient
        self.terms: list[tuple[Tensors, Tensors]] = []

    def penalty(self, model: nn.Module) -> torch.Tensor | None:
        if not self.terms or self.coefficient == 0:
            return None
        params = dict(model.named_parameters())
        total = None
        for importance, anchor in self.terms:
            for name, weight in importance.items():
                term = torch.sum(weight * (params[name] - anchor[name]) ** 2)
                total = term if total is None else total + term
        return self.coefficient * total

    def loss(self, ctx, x, y, outputs, loss):
        extra = self.penalty(ctx.model)
        return loss if extra is None else loss + extra

    def state_dict(self) -> dict:
        return {"terms": [(dict(i), dict(a)) for i, a in self.terms]}

    def load_state_dict(self, state: dict) -> None:
        self.terms = [(dict(i), dict(a)) for i, a in state.get("terms", [])]


def snapshot(model: nn.Module) -> Tensors:
    """A detached copy of every trainable parameter."""
    return {n: p.detach().clone() for n, p in model.named_parameters() if p.requires_grad}


# A per-sample objective: (the outputs of one scene (outputs,), its targets (outputs,),
# a tensor of that scene's own (noise, or nothing)) -> a scalar.
SampleObjective = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def per_sample_importance(
    model: nn.Module,
    batches: Iterable[tuple[torch.Tensor, torch.Tensor]],
    objective: SampleObjective,
    reduce: Callable[[torch.Tensor], torch.Tensor] = torch.square,
    max_batches: int | None = None,
    extra: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> Tensors:
    """Mean over the scenes of ``reduce(d objective / d theta)``, one gradient per scene,
    per trainable parameter: the empirical Fisher's diagonal with ``torch.square`` over
    each scene's loss (Kirkpatrick et al. 2017), MAS's importance with ``torch.abs`` over
    each scene's squared output norm (Aljundi et al. 2018, eq. 4).

    The gradients are ``torch.func.vmap`` of ``grad`` over each batch's scenes (one call per
    batch, not one backward per scene), with the model in eval mode: BatchNorm uses its
    running statistics, so a scene's gradient does not depend on the other scenes of its
    batch, and they are left untouched. ``extra(targets)`` draws a tensor per scene passed
    to the objective (the ``model`` Fisher's noise), in the batches' order.
    """
    trained = {n: p.detach() for n, p in model.named_parameters() if p.requires_grad}
    fixed = {n: p.detach() for n, p in model.named_parameters() if not p.requires_grad}
    fixed |= dict(model.named_buffers())

    def scene(params: Tensors, x: torch.Tensor, y: torch.Tensor, e: torch.Tensor):
        out = functional_call(model, (params, fixed), (x.unsqueeze(0),))
        return objective(out.squeeze(0).float(), y, e)

    per_scene = vmap(grad(scene), in_dims=(None, 0, 0, 0))
    total = {n: torch.zeros_like(p) for n, p in trained.items()}
    count = 0
    with eval_mode(model):
        for x, y in itertools.islice(batches, max_batches):
            e = extra(y) if extra is not None else torch.zeros(len(x), device=x.device)
            for n, g in per_scene(trained, x, y, e).items():
                total[n] += reduce(g).sum(dim=0)
            count += len(x)
    return {n: t / max(count, 1) for n, t in total.items()}


def gradient_importance(
    model: nn.Module,
    batches: Iterable[tuple[torch.Tensor, torch.Tensor]],
    objective: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    reduce: Callable[[torch.Tensor], torch.Tensor] = torch.square,
    max_batches: int | None = None,
) -> Tensors:
    """Mean over batches of ``reduce(d objective / d theta)`` per trainable parameter.

    ``objective(outputs, y)`` is a scalar per batch; gradients are per mini-batch (as in
    Avalanche's EWC and MAS plugins), with the model in eval mode so that BatchNorm
    statistics are used and left untouched. The published methods take one gradient per
    scene (:func:`per_sample_importance`); this form stays for reproducing runs made with
    it (``continual.ewc.fisher=batch``, ``continual.mas.importance=batch``).
    """
    params = {n: p for n, p in model.named_parameters() if p.requires_grad}
    total = {n: torch.zeros_like(p) for n, p in params.items()}
    count = 0
    with eval_mode(model):
        try:
            for x, y in itertools.islice(batches, max_batches):
                model.zero_grad(set_to_none=True)
                objective(model(x).float(), y).backward()
                for n, p in params.items():
                    if p.grad is not None:
                        total[n] += reduce(p.grad.detach())
                count += 1
        finally:
            model.zero_grad(set_to_none=True)
    return {n: t / max(count, 1) for n, t in total.items()}
