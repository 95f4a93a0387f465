"""Test metrics (SPEC 5) with torchmetrics, over the whole test set.

Per action: MSE, RMSE and Pearson correlation; reported: their means over the 8 actions
(``loss`` = mean MSE, ``rmse`` = mean of per-action RMSE, ``pcc`` = mean of per-action
PCC). A constant prediction column has PCC 0, never NaN. ``batch_compat=True`` reproduces
the reference code's biased figures: metrics per test batch of 16, averaged over batches.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torchmetrics.functional import mean_squared_error, pearson_corrcoef

COMPAT_BATCH = 16
_CONSTANT = 1e-6  # a prediction column with a smaller standard deviation is constant


@dataclass(frozen=True)
class RegressionScores:
    mse: torch.Tensor  # (8,) per action
    rmse: torch.Tensor  # (8,)
    pcc: torch.Tensor  # (8,)

    @property
    def loss(self) -> float:
        return float(self.mse.mean())

    @property
    def mean_rmse(self) -> float:
        return float(self.rmse.mean())

    @property
    def mean_pcc(self) -> float:
        return float(self.pcc.mean())


def _scores(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, ...]:
    pred, target = pred.double(), target.double()
    n = pred.shape[1]
    mse = mean_squared_error(pred, target, num_outputs=n)
    if len(pred) < 2:
        return mse, mse.sqrt(), torch.zeros(n, dtype=pred.dtype)
    # A constant column has no correlation: 0 (torchmetrics would warn and give NaN, or a
    # spurious ~1e-8 for a constant non-zero float32 column).
    varies = (pred.std(dim=0) >= _CONSTANT) & (target.std(dim=0) >= _CONSTANT)
    pcc = torch.zeros(n, dtype=pred.dtype)
    if varies.any():
        pcc[varies] = pearson_corrcoef(pred[:, varies], target[:, varies]).reshape(-1)
    return mse, mse.sqrt(), pcc


def regression_scores(
    pred: torch.Tensor, target: torch.Tensor, batch_compat: bool = False
) -> RegressionScores:
    """Scores of ``pred`` against ``target`` (both (N, 8)), whole-set or batch-averaged."""
    pred, target = pred.detach().cpu(), target.detach().cpu()
    if not batch_compat:
        return RegressionScores(*(s.float() for s in _scores(pred, target)))
    per_batch = [
        _scores(pred[i : i + COMPAT_BATCH], target[i : i + COMPAT_BATCH])
        for i in range(0, len(pred), COMPAT_BATCH)
    ]
    mse, rmse, pcc = (
        torch.stack(parts).mean(dim=0).float() for parts in zip(*per_batch, strict=True)
    )
    return RegressionScores(mse, rmse, pcc)
