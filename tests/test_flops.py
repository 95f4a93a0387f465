"""``fedlgr.core.meters.flops``: the operation count of a training step, with the grouped
convolution backward formula that torch 2.15 gets wrong (issue 48, the methods check of
2026-12-07), on hand arithmetic; and ``bench/flops.py``'s peak and its smoke run.

Every count is on the meta device (shapes only) and exact: integers, no tolerance."""

from __future__ import annotations

import contextlib
import copy
import importlib
import math
import subprocess
import sys

import pytest
import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from fedlgr.core.client.training import flops_per_sample
from fedlgr.core.meters.flops import flop_counter
from fedlgr.core.models.scholar import build_scholar
from fedlgr.shell.config import CONF_DIR, load_config
from tests.support.checkout import REPO

CONV = torch.ops.aten.convolution
CONV_BACKWARD = torch.ops.aten.convolution_backward


def counts(counter_of, model: nn.Module, x_shape, input_grad: bool) -> dict:
    """The count of each operator of ``model``'s forward and backward on a meta input."""
    model = model.to("meta")
    x = torch.empty(x_shape, device="meta", requires_grad=input_grad)
    with counter_of() as counter:
        model(x).sum().backward()
    return dict(counter.get_flop_counts()["Global"])


def torch_counter() -> FlopCounterMode:
    return FlopCounterMode(display=False)


def depthwise(bias: bool = False) -> nn.Module:
    return nn.Conv2d(64, 64, 3, padding=1, groups=64, bias=bias)


# A depthwise 3x3 convolution over 64 channels at 32x32, one image: one multiply-add (2
# operations) per weight (64 x 1 x 3 x 3) and output position (32 x 32).
DEPTHWISE_FORWARD = 2 * 64 * 9 * 32 * 32
assert DEPTHWISE_FORWARD == 1_179_648


def test_a_depthwise_convolution_s_backward_is_twice_its_forward():
    """Input and weight gradients each repeat the forward's multiply-adds: backward = 2x
    forward; with an input that needs no gradient (a network's first layer) only the
    weight gradient is computed: 1x."""
    both = counts(flop_counter, depthwise(), (1, 64, 32, 32), input_grad=True)
    assert both == {CONV: 1_179_648, CONV_BACKWARD: 2_359_296}
    weight_only = counts(flop_counter, depthwise(), (1, 64, 32, 32), input_grad=False)
    assert weight_only == {CONV: 1_179_648, CONV_BACKWARD: 1_179_648}
    frozen = depthwise().requires_grad_(False)
    assert counts(flop_counter, frozen, (1, 64, 32, 32), input_grad=True) == weight_only
    assert both[CONV] == DEPTHWISE_FORWARD


def test_torch_s_own_count_is_the_bug_this_corrects():
    """torch 2.15 counts the weight gradient 64x over (the groups are lost in the
    transposed shapes, pytorch/pytorch PR #183405); its forward count is right. When this
    fails, torch has fixed its formula and ``fedlgr.core.meters.flops`` can go."""
    assert counts(torch_counter, depthwise(), (1, 64, 32, 32), input_grad=False) == {
        CONV: DEPTHWISE_FORWARD,
        CONV_BACKWARD: 64 * DEPTHWISE_FORWARD,
    }


def test_the_bias_gradient_counts_nothing_as_the_bias_does_forward():
    with_bias = counts(flop_counter, depthwise(bias=True), (1, 64, 32, 32), input_grad=True)
    assert with_bias == counts(flop_counter, depthwise(), (1, 64, 32, 32), input_grad=True)


def test_grouped_and_strided_convolutions_on_hand_numbers():
    """8 -> 16 channels in 4 groups, 3x3, stride 2, padding 1, 3 images of 9x9: weight
    16 x 2 x 3 x 3 = 288, output 5 x 5 (``(9 + 2 - 3) // 2 + 1``)."""
    conv = nn.Conv2d(8, 16, 3, stride=2, padding=1, groups=4)
    forward = 2 * 3 * 288 * 25
    assert forward == 43_200
    assert counts(flop_counter, conv, (3, 8, 9, 9), input_grad=True) == {
        CONV: 43_200,
        CONV_BACKWARD: 86_400,
    }


def test_a_grouped_transposed_convolution_on_hand_numbers():
    """A transposed convolution slides over its input: 8 -> 16 channels in 4 groups, 4x4,
    stride 2, 2 images of 5x5: weight 8 x 4 x 4 x 4 = 512, 25 input positions (its output
    is 10x10)."""
    conv = nn.ConvTranspose2d(8, 16, 4, stride=2, padding=1, groups=4)
    forward = 2 * 2 * 512 * 25
    assert forward == 51_200
    assert counts(flop_counter, conv, (2, 8, 5, 5), input_grad=True) == {
        CONV: 51_200,
        CONV_BACKWARD: 102_400,
    }
    assert counts(flop_counter, conv, (2, 8, 5, 5), input_grad=False)[CONV_BACKWARD] == 51_200


def dense() -> nn.Module:
    """Convolutions with groups=1 (strided, padded, dilated, transposed, with and without a
    bias) and linear layers: where torch's formulas are right."""
    return nn.Sequential(
        nn.Conv2d(3, 8, 3, stride=2, padding=1),
        nn.BatchNorm2d(8),
        nn.ReLU(),
        nn.Conv2d(8, 8, 3, dilation=2, bias=False),
        nn.ConvTranspose2d(8, 4, 2, stride=2),
        nn.Flatten(),
        nn.Linear(4 * 8 * 8, 16),
        nn.Linear(16, 8, bias=False),
    )


@pytest.mark.parametrize("input_grad", [True, False])
def test_dense_layers_count_as_torch_counts_them(input_grad):
    ours = counts(flop_counter, dense(), (2, 3, 16, 16), input_grad)
    theirs = counts(torch_counter, dense(), (2, 3, 16, 16), input_grad)
    assert ours == theirs
    assert ours[CONV_BACKWARD] > 0 and ours[torch.ops.aten.mm] > 0


def test_a_1d_dense_convolution_counts_as_torch_counts_it():
    conv = nn.Conv1d(4, 6, 5, padding=2)
    ours = counts(flop_counter, conv, (3, 4, 20), input_grad=True)
    assert ours == counts(torch_counter, conv, (3, 4, 20), input_grad=True)
    assert ours[CONV] == 2 * 3 * (6 * 4 * 5) * 20  # 14,400


@pytest.fixture(scope="module")
def demo_model() -> nn.Module:
    """The demo's scholar as fedlgr builds it: half-width MobileNetV2 root + top, 128 px,
    channels_last."""
    config = load_config(CONF_DIR / "experiment" / "demo.yaml", ["data.path=unused"])
    assert (config.model.width, config.data.image_size) == (0.5, 128)
    return build_scholar(config).train()


# Half-width MobileNetV2's stem: 3 -> 16 channels, 3x3, stride 2: 128 px -> 64x64 outputs.
STEM_FORWARD = 2 * (16 * 3 * 3 * 3) * 64 * 64
assert STEM_FORWARD == 3_538_944


def test_mobilenet_v2_trains_at_about_three_times_its_forward(demo_model):
    """Every convolution and linear layer's backward is 2x its forward except the stem's,
    whose input (the image) needs no gradient: 1x. So training = 3 x forward - stem, per
    image, exactly (BatchNorm, ReLU and the pool count nothing, in torch's convention too);
    2.94x. torch's own count makes it 18x."""
    x = torch.empty(16, 3, 128, 128, device="meta")
    meta = _meta_copy(demo_model)
    with flop_counter() as counter:
        meta(x)
    forward = counter.get_total_flops() / 16
    with flop_counter() as counter:
        meta(x).sum().backward()
    training = counter.get_total_flops() / 16
    assert training == 3 * forward - STEM_FORWARD
    assert 2.5 <= training / forward <= 3.5
    assert math.isclose(training / forward, 2.94, abs_tol=0.005)


def test_flops_per_sample_is_the_corrected_count(demo_model):
    """The count fedlgr logs (``cost/gflops``) is this module's, not torch's own."""
    meta = _meta_copy(demo_model)
    x = torch.empty(4, 3, 128, 128, device="meta")
    with flop_counter() as ours, torch_counter() as theirs:  # nested: both see every op
        meta(x).float().sum().backward()
    logged = flops_per_sample(demo_model, torch.zeros(4, 3, 128, 128))
    assert logged == ours.get_total_flops() / 4
    assert logged < theirs.get_total_flops() / 4 / 6  # torch's own: 18x forward, ours 2.94x


def _meta_copy(model: nn.Module) -> nn.Module:
    return copy.deepcopy(model).to("meta")


# --- bench/flops.py ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def bench():
    """``bench/flops.py``, imported as the scripts import each other (from their folder)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(REPO / "bench"))
        yield importlib.import_module("flops")
    for name in ("flops", "figures"):
        sys.modules.pop(name, None)


ZEN4 = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 25
model\t\t: 17
model name\t: AMD EPYC
cpu MHz\t\t: 2596.128
flags\t\t: fpu sse sse2 fma avx avx2 avx512f avx512dq avx512bw avx512vl
"""
SKYLAKE_SP = """vendor_id\t: GenuineIntel
cpu family\t: 6
model name\t: Intel(R) Xeon(R) Gold 6148 CPU @ 2.40GHz
cpu MHz\t\t: 2400.000
flags\t\t: fpu sse sse2 fma avx avx2 avx512f
"""
HASWELL = """vendor_id\t: GenuineIntel
cpu family\t: 6
flags\t\t: fpu sse sse2 fma avx avx2
"""


def test_the_core_s_peak_from_its_flags_and_clock(bench):
    """lanes x FMA units x 2 x GHz: Zen 4 runs AVX-512 on 256-bit FMA pipes (8 lanes);
    an Intel AVX-512 core has 16; cpufreq's maximum beats ``cpu MHz``; with no clock
    visible the assumed one is said."""
    zen4 = bench.core_peak(ZEN4, None, None, 2)
    assert (zen4.lanes, zen4.units, zen4.ghz) == (8, 2, 2.596128)
    assert zen4.gflop_per_s == pytest.approx(8 * 2 * 2 * 2.596128, rel=1e-12)
    assert "2 FMA units (assumed" in zen4.why and "cpu MHz" in zen4.why
    intel = bench.core_peak(SKYLAKE_SP, "3700000", None, 2)
    assert (intel.lanes, intel.ghz) == (16, 3.7) and "cpufreq" in intel.why
    assert bench.core_peak(SKYLAKE_SP, "3700000", 2.0, 1).gflop_per_s == 16 * 1 * 2 * 2.0
    haswell = bench.core_peak(HASWELL, None, None, 2)
    assert (haswell.lanes, haswell.ghz) == (8, bench.ASSUMED_GHZ) and "ASSUMED" in haswell.why


@pytest.mark.slow
def test_the_benchmark_runs_a_round_below_the_peak(tmp_path):
    """``bench/flops.py`` on 40 scenes at 32 px (~10 s): every figure printed, the rate is
    the round's GFLOP over its CPU seconds and under the peak, and the training count is
    2.5-3.5x the forward."""
    done = subprocess.run(
        [sys.executable, str(REPO / "bench" / "flops.py"), "--scenes", "40", "--size", "32"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    figures = {}
    for line in done.stdout.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].isidentifier():
            with contextlib.suppress(ValueError):  # the other lines: words, not figures
                figures[parts[0]] = float(parts[1])
    names = ("round_gflop", "round_cpu_s", "gflop_per_cpu_s", "peak_gflop_per_s")
    assert all(figures[n] > 0 for n in names), figures
    # Printed to 2 decimals, each off by at most 0.005: the rate lies between the ratios
    # of the printed figures moved by that much.
    gflop, cpu_s, rate = (figures[n] for n in names[:3])
    assert (gflop - 0.005) / (cpu_s + 0.005) - 0.005 <= rate <= (gflop + 0.005) / (cpu_s - 0.005)
    assert rate < figures["peak_gflop_per_s"]
    assert "share_of_peak" in done.stdout and "2 FMA units (assumed" in done.stdout
    ratio = float(done.stdout.split("x forward;")[0].rsplit("(", 1)[1])
    assert 2.5 <= ratio <= 3.5
