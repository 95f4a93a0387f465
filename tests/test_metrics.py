"""Test metrics on hand-checkable numbers, and the resource meter."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch

from fedlgr.core.meters.costs import measure, nvml_available
from fedlgr.core.meters.scores import compat_order, regression_scores


def test_scores_by_hand():
    target = torch.tensor([[1.0, 2.0], [2.0, 4.0], [3.0, 6.0], [4.0, 8.0]])
    pred = torch.tensor([[1.0, 8.0], [2.0, 6.0], [3.0, 4.0], [5.0, 2.0]])
    s = regression_scores(pred, target)
    # Column 0: errors 0,0,0,1 -> MSE 0.25; column 1: 6,2,-2,-6 -> MSE 20.
    assert s["loss"].tolist() == pytest.approx([0.25, 20.0])  # per action: MSE
    assert s["rmse"].tolist() == pytest.approx([0.5, math.sqrt(20.0)])
    assert s["pcc"][1].item() == pytest.approx(-1.0)
    assert s["pcc"][0].item() == pytest.approx(0.9827076, abs=1e-6)  # corr([1,2,3,5],[1,2,3,4])
    # Lin's CCC, moments over n: column 0 has means 2.75 and 2.5, covariance 1.625,
    # variances 2.1875 and 1.25: 2 x 1.625 / (2.1875 + 1.25 + 0.25^2) = 3.25 / 3.5;
    # column 1 is the ratings reversed: -1.
    assert s["ccc"].tolist() == pytest.approx([3.25 / 3.5, -1.0])
    assert s.mean("loss") == pytest.approx(10.125)
    # not the RMSE of all errors
    assert s.mean("rmse") == pytest.approx((0.5 + math.sqrt(20.0)) / 2)


def test_constant_prediction_has_zero_pcc_not_nan():
    target = torch.tensor([[1.0, 2.0], [2.0, 3.0], [4.0, 1.0]])
    for value in (0.0, 3.1):
        s = regression_scores(torch.full((3, 2), value), target)
        assert s["pcc"].tolist() == [0.0, 0.0] == s["ccc"].tolist()
        assert not torch.isnan(s["loss"]).any()


def test_ccc_counts_a_shift_and_a_scale_that_pcc_forgives():
    """CCC is agreement: ratings shifted by 1 or doubled keep PCC at 1, not CCC.
    Ratings 1..5 (mean 3, variance 2 over n): shifted by 1, 2 x 2 / (2 + 2 + 1) = 0.8;
    doubled (variance 8, covariance 4, means 6 and 3), 2 x 4 / (8 + 2 + 9) = 8 / 19."""
    target = torch.tensor([[1.0], [2.0], [3.0], [4.0], [5.0]])
    for pred, ccc in ((target + 1, 0.8), (2 * target, 8 / 19), (target, 1.0)):
        s = regression_scores(pred, target)
        assert s["pcc"].item() == pytest.approx(1.0)
        assert s["ccc"].item() == pytest.approx(ccc)
    figures = regression_scores(target + 1, target).figures("test")
    assert figures["test/ccc"] == pytest.approx(0.8) and figures["test/pcc"] == pytest.approx(1)


def _three_batches() -> tuple[torch.Tensor, torch.Tensor]:
    """50 rows: three batches of 16 and 2 rows the LEAP-HRI'24 code drops (drop_last).
    Every column's ratings alternate 2, 4 in each batch. Batch 1 is off by +1 everywhere
    (RMSE 1, PCC 1); batch 2 is right on actions 0-3 and off by +1 on 4-7 (flattened MSE
    0.5, RMSE sqrt(0.5); the mean of its per-action RMSE is 0.5; PCC 1); batch 3 is the
    ratings mirrored, 6 - t, off by -2 and +2 (RMSE 2, PCC -1); the 2 left over are 100."""
    target = torch.tensor([2.0, 4.0]).repeat(25)[:, None].expand(50, 8).clone()
    pred = target.clone()
    pred[:16] += 1
    pred[16:32, 4:] += 1
    pred[32:48] = 6 - target[32:48]
    pred[48:] = 100.0
    return pred, target


def test_batch_compat_is_the_leap_hri24_definition_by_hand():
    """The LEAP-HRI'24 code's test(): per batch of 16 the MSE and the RMSE of the flattened
    batch and each action's PCC; means over the batches (Federated Continual
    Learning/utils.py in nchuramani/FCL-MannersDB)."""
    pred, target = _three_batches()
    s = regression_scores(pred, target, batch_compat=True)
    # exact in float64, then one rounding to float32 / a Python float: 1e-6 covers it
    assert s.mean("loss") == pytest.approx((1 + 0.5 + 4) / 3, abs=1e-6)
    assert s.mean("rmse") == pytest.approx((1 + math.sqrt(0.5) + 2) / 3, abs=1e-6)
    assert s.mean("pcc") == pytest.approx((1 + 1 - 1) / 3, abs=1e-6)
    assert s["pcc"].tolist() == pytest.approx([1 / 3] * 8, abs=1e-6)
    # per action, the RMSE of each action's column per batch: 1, 0 or 1, 2
    assert s["rmse"].tolist() == pytest.approx([1.0] * 4 + [4 / 3] * 4, abs=1e-6)
    figures = s.figures("test")
    assert figures["test/rmse"] == pytest.approx((3 + math.sqrt(0.5)) / 3, abs=1e-6)
    # the same rows over the whole set: the 2 dropped rows count, batches do not
    whole = regression_scores(pred, target)
    assert whole.mean("rmse") > 10 and whole.mean("pcc") != pytest.approx(1 / 3, abs=0.1)


def test_batch_compat_matches_an_independent_loop_on_random_numbers():
    """The definition again, written as that code's loop (numpy Pearson per column, the
    flattened batch's MSE): random ratings, 5 batches and 7 rows dropped."""
    g = torch.Generator().manual_seed(0)
    target = torch.rand(87, 8, generator=g, dtype=torch.float64) * 4 + 1
    pred = target + 0.7 * torch.randn(87, 8, generator=g, dtype=torch.float64)
    loss, rmse, pcc = [], [], []
    for i in range(0, 80, 16):
        p, t = pred[i : i + 16].numpy(), target[i : i + 16].numpy()
        mse = ((p - t) ** 2).mean()
        loss.append(mse)
        rmse.append(math.sqrt(mse))
        pcc.append([np.corrcoef(t[:, a], p[:, a])[0, 1] for a in range(8)])
    s = regression_scores(pred, target, batch_compat=True)
    assert s.mean("loss") == pytest.approx(np.mean(loss), abs=1e-6)  # float32 per action
    assert s.mean("rmse") == pytest.approx(np.mean(rmse), abs=1e-12)  # kept in float64
    assert s["pcc"].tolist() == pytest.approx(np.mean(pcc, axis=0).tolist(), abs=1e-6)


def test_batch_compat_with_fewer_rows_than_a_batch_scores_them_as_one():
    pred, target = _three_batches()
    whole = regression_scores(pred[:10], target[:10])
    compat = regression_scores(pred[:10], target[:10], batch_compat=True)
    assert compat.mean("pcc") == pytest.approx(whole.mean("pcc"), abs=1e-6)
    assert compat.mean("rmse") == pytest.approx(1.0, abs=1e-6)  # all off by 1


def test_compat_order_shuffles_each_task_the_same_everywhere():
    rows = torch.arange(40)
    first, again = compat_order(rows, 0), compat_order(rows, 0)
    assert torch.equal(first, again) and not torch.equal(first, rows)
    assert sorted(first.tolist()) == rows.tolist()
    assert not torch.equal(compat_order(rows, 1), first)  # each task its own order


def test_measure_counts_cpu_seconds_of_this_process():
    with measure(torch.device("cpu")) as usage:
        end = time.process_time() + 0.3
        while time.process_time() < end:
            pass
    assert 0.25 <= usage.cpu_s <= 1.0
    assert usage.wall_s >= 0.25
    assert usage.gpu_util is None and usage.gpu_mem_mb is None  # a CPU device: absent


def test_nvml_absence_is_not_an_error():
    assert nvml_available() in (True, False)
