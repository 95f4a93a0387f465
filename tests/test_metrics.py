"""Test metrics on hand-checkable numbers, and the resource meter."""

from __future__ import annotations

import math
import time

import pytest
import torch

from fedlgr.core.meters.costs import measure, nvml_available
from fedlgr.core.meters.scores import regression_scores


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


def test_batch_compat_mode_averages_per_batch():
    torch.manual_seed(0)
    target = torch.rand(40, 8) * 4 + 1
    pred = target + 0.5 * torch.randn(40, 8)
    whole = regression_scores(pred, target)
    compat = regression_scores(pred, target, batch_compat=True)
    by_hand = torch.stack(
        [regression_scores(pred[i : i + 16], target[i : i + 16])["pcc"] for i in (0, 16, 32)]
    )
    assert compat["pcc"].tolist() == pytest.approx(by_hand.mean(0).tolist(), abs=1e-6)
    assert compat.mean("pcc") != pytest.approx(whole.mean("pcc"), abs=1e-4)


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
