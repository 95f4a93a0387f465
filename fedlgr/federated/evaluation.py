"""Every client evaluates its own model on the shared test set (SPEC 5)."""

from __future__ import annotations

import contextlib

import torch
from torch import nn

from fedlgr.tracking.metrics import RegressionScores, regression_scores


@torch.no_grad()
def predict(
    model: nn.Module, inputs: torch.Tensor, batch_size: int, autocast=contextlib.nullcontext
) -> torch.Tensor:
    """Model outputs (N, 8) for prepared (normalised, on-device) inputs, in eval mode."""
    was_training = model.training
    model.eval()
    try:
        with autocast():
            out = [
                model(inputs[i : i + batch_size]).float() for i in range(0, len(inputs), batch_size)
            ]
    finally:
        model.train(was_training)
    return torch.cat(out)


@torch.no_grad()
def predict_tops(
    root: nn.Module,
    tops: list[nn.Module],
    inputs: torch.Tensor,
    batch_size: int,
    autocast=contextlib.nullcontext,
) -> list[torch.Tensor]:
    """``predict`` of models ``top_i(root(x))`` that share ``root``: the root's pass once
    per batch, then every top on it (the same batches, hence the same numbers as
    ``predict`` of each whole model)."""
    modules = [root, *tops]
    was_training = [m.training for m in modules]
    for m in modules:
        m.eval()
    outputs: list[list[torch.Tensor]] = [[] for _ in tops]
    try:
        with autocast():
            for i in range(0, len(inputs), batch_size):
                latents = root(inputs[i : i + batch_size])
                for out, top in zip(outputs, tops, strict=True):
                    out.append(top(latents).float())
    finally:
        for m, training in zip(modules, was_training, strict=True):
            m.train(training)
    return [torch.cat(out) for out in outputs]


def evaluate(
    model: nn.Module,
    inputs: torch.Tensor,
    targets: torch.Tensor,
    batch_size: int,
    autocast=contextlib.nullcontext,
    batch_compat: bool = False,
) -> RegressionScores:
    return regression_scores(predict(model, inputs, batch_size, autocast), targets, batch_compat)
