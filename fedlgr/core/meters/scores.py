"""Test scores with torchmetrics, over the whole test set: every score of
:data:`fedlgr.core.metrics.SCORES`, per action, by its name.

``loss`` is the per-action MSE, ``rmse`` its square root, ``pcc`` the Pearson correlation,
``ccc`` Lin's concordance correlation (agreement: 1 only where the predictions equal the
ratings, where PCC forgives a shift and a scale); a score is reported as its mean over
the 8 actions (the mean of per-action RMSE is not the RMSE of the flattened data). A
constant prediction column has PCC and CCC 0, never NaN.

``batch_compat=True`` gives the LEAP-HRI'24 benchmark's figures instead (Checker, Churamani
& Gunes 2024; nchuramani/FCL-MannersDB, ``Federated Continual Learning/utils.py``,
``test``): the rows cut into batches of 16 in the order given, a last partial batch
dropped (``drop_last``); per batch the MSE and the RMSE of the flattened 16 x 8 errors and
each action's Pearson correlation; the loss and RMSE are their means over the batches, the
PCC each action's mean over the batches, averaged over the actions. A batch is scored
like the whole set otherwise (a constant column's PCC is 0, where that code correlates
the labels with the outputs plus N(0, 1e-7) noise). Biased: a batch's PCC is not the
whole set's (docs/leap_hri24.md).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torchmetrics.functional import mean_squared_error, pearson_corrcoef

from fedlgr.core.data.columns import LABEL_SHORT_NAMES
from fedlgr.core.metrics import SCORES, Figures

COMPAT_BATCH = 16  # the LEAP-HRI'24 code's test batch (drop_last)
COMPAT_ORDER_SEED = 2024  # any fixed number: that code draws its order unseeded
_CONSTANT = 1e-6  # a prediction column with a smaller standard deviation is constant

PerAction = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # (N, 8) x 2 -> (8,)


def _mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return mean_squared_error(pred, target, num_outputs=pred.shape[1])


def _rmse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return _mse(pred, target).sqrt()


def _varies(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The actions whose prediction and target both vary: a constant column has no
    correlation (torchmetrics would warn and give NaN, or a spurious ~1e-8 for a constant
    non-zero float32 column)."""
    if len(pred) < 2:
        return torch.zeros(pred.shape[1], dtype=torch.bool)
    return (pred.std(dim=0) >= _CONSTANT) & (target.std(dim=0) >= _CONSTANT)


def _pcc(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    varies = _varies(pred, target)
    pcc = torch.zeros(pred.shape[1], dtype=pred.dtype)
    if varies.any():
        pcc[varies] = pearson_corrcoef(pred[:, varies], target[:, varies]).reshape(-1)
    return pcc


def _ccc(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Lin's (1989) concordance correlation, 2 s_xy / (s_x^2 + s_y^2 + (mean_x - mean_y)^2),
    with the moments over n as Lin estimates them; a constant column's is 0 (its
    covariance is). Not torchmetrics' concordance_corrcoef: it takes the variances over
    n - 1 beside the squared mean difference, which is not Lin's estimator (1e-3 apart on
    40 scenes)."""
    varies = _varies(pred, target)
    ccc = torch.zeros(pred.shape[1], dtype=pred.dtype)
    if varies.any():
        x, y = pred[:, varies], target[:, varies]
        dx, dy = x - x.mean(dim=0), y - y.mean(dim=0)
        covariance = (dx * dy).mean(dim=0)
        gap = (x.mean(dim=0) - y.mean(dim=0)) ** 2
        ccc[varies] = 2 * covariance / ((dx**2).mean(dim=0) + (dy**2).mean(dim=0) + gap)
    return ccc


# Every score's per-action function, by the name it has in fedlgr.core.metrics.SCORES;
# they take and give float64.
PER_ACTION: dict[str, PerAction] = {"loss": _mse, "rmse": _rmse, "pcc": _pcc, "ccc": _ccc}


class RegressionScores:
    """Every score of some outputs, per action (``scores["rmse"]``: a (8,) float32 tensor).

    ``reported``: scores whose reported figure is not the mean of their per-action ones
    (the batch-compatible RMSE, of the flattened batch)."""

    def __init__(
        self, per_action: dict[str, torch.Tensor], reported: dict[str, float] | None = None
    ):
        self.per_action = per_action
        self.reported = reported or {}

    def __getitem__(self, name: str) -> torch.Tensor:
        return self.per_action[name]

    def mean(self, name: str) -> float:
        """The score ``name`` as reported: its mean over the actions."""
        if name in self.reported:
            return self.reported[name]
        return float(self.per_action[name].mean())

    def figures(self, prefix: str, per_action: bool = False) -> Figures:
        """``{prefix/<score>: mean}`` (``test/rmse``), with ``per_action`` every score's
        per-action figure too (``test/rmse/vacuum``, ``test/mse/vacuum``)."""
        out = {f"{prefix}/{s.name}": self.mean(s.name) for s in SCORES}
        if per_action:
            for s in SCORES:
                values = self.per_action[s.name].tolist()
                out |= {
                    f"{prefix}/{s.per_action}/{a}": v
                    for a, v in zip(LABEL_SHORT_NAMES, values, strict=True)
                }
        return out


def _scores(pred: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
    pred, target = pred.double(), target.double()
    return {s.name: PER_ACTION[s.name](pred, target) for s in SCORES}


def regression_scores(
    pred: torch.Tensor, target: torch.Tensor, batch_compat: bool = False
) -> RegressionScores:
    """Scores of ``pred`` against ``target`` (both (N, 8)): over the whole set, or with
    ``batch_compat`` as the LEAP-HRI'24 code scores them (:func:`batch_scores`)."""
    pred, target = pred.detach().cpu(), target.detach().cpu()
    if batch_compat:
        return batch_scores(pred, target)
    return RegressionScores({k: v.float() for k, v in _scores(pred, target).items()})


def batch_scores(
    pred: torch.Tensor, target: torch.Tensor, batch: int = COMPAT_BATCH
) -> RegressionScores:
    """The LEAP-HRI'24 benchmark's scores: per batch of ``batch`` consecutive rows (the
    last partial batch dropped; fewer rows than a batch make one batch), averaged over the
    batches. Per action: every score's mean over the batches; reported: the loss and the
    RMSE of each flattened batch, averaged over the batches (the mean of per-action RMSE is
    not the RMSE of the flattened batch), the others the mean over the actions."""
    pred, target = pred.detach().cpu().double(), target.detach().cpu().double()
    starts = range(0, max(len(pred) // batch, 1) * batch, batch)
    cuts = [(pred[i : i + batch], target[i : i + batch]) for i in starts]
    per_batch = [_scores(p, t) for p, t in cuts]
    flat_mse = torch.stack([((p - t) ** 2).mean() for p, t in cuts])
    per_action = {
        s.name: torch.stack([b[s.name] for b in per_batch]).mean(dim=0).float() for s in SCORES
    }
    reported = {"loss": float(flat_mse.mean()), "rmse": float(flat_mse.sqrt().mean())}
    return RegressionScores(per_action, reported)


def compat_order(rows: torch.Tensor, task: int) -> torch.Tensor:
    """A task's test rows in the order the LEAP-HRI'24 code scores them: shuffled (its
    splitter shuffles each context's scenes before taking the last quarter as the test
    set), seeded by the task's place in the schedule so that every client and the server
    cut the same batches. Its test set after Task 2 is Task 1's shuffled rows followed by
    Task 2's: the caller concatenates them."""
    generator = torch.Generator().manual_seed(COMPAT_ORDER_SEED + task)
    return rows[torch.randperm(len(rows), generator=generator)]
