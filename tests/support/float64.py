"""Batched and sequential client training compared in float64 (tests/test_batched.py's
docstring says why float64): the tolerance, and a client's batches in float64."""

from __future__ import annotations

import torch

from fedlgr.core.data.augment import SceneBatches

# float64, measured over these tests: weights and BatchNorm statistics differ by 1.7e-8 at
# most (biases whose true gradient is 0, where Adam scales up the remaining noise), Adam's
# second moments by 1.3e-6 absolute on values ~10 (1e-7 relative). One Adam step moves a
# weight by ~lr = 1e-3, so a skipped step or a swapped client fails by 4 orders of magnitude.
TIGHT = {"rtol": 1e-5, "atol": 1e-7}
# ... plus a term set by each tensor's largest entry. The loss is taken in float32: the
# float64 outputs are rounded to float32 first, and the two paths' outputs differ by float64
# rounding (~1e-16, in the last bit on some kernels and not on others), so now and then one
# output rounds to the neighbouring float32 and its gradient moves by 2^-24 of its size.
# That error spreads over a whole tensor through the backward pass, so near-zero entries of
# a tensor carry an error that scales with the tensor's largest entry, not with their own:
# an Intel Xeon (AVX-512/AMX) showed 5.2e-7 on one entry of a depthwise weight's Adam first
# moment, against TIGHT's 1e-7 (those tensors' entries reach 1-40 here). Multiplying the
# batched outputs by 1 + 1e-15 .. 1e-13 here reproduces it (1 of 432 entries off by 1.5e-7
# .. 5.8e-7), and the largest excess over TIGHT was 1.3e-10 of the tensor's largest entry.
# 16 float32 ulps of the largest entry (9.5e-7 of it) covers that 7000-fold, and a skipped
# Adam step (1e-3 on weights <= ~1, 10% of a moment) still fails by 3 orders of magnitude.
SCALE_ULPS = 16 * torch.finfo(torch.float32).eps / 2  # 2^-20


def assert_close_f64(actual: torch.Tensor, expected: torch.Tensor, msg=None) -> None:
    """``actual`` equals ``expected`` to TIGHT plus SCALE_ULPS of ``expected``'s largest entry."""
    scale = expected.abs().max().item() if expected.is_floating_point() and expected.numel() else 0
    torch.testing.assert_close(
        actual, expected, rtol=TIGHT["rtol"], atol=TIGHT["atol"] + SCALE_ULPS * scale, msg=msg
    )


class Float64Batches:
    """A client's batches with float64 inputs (same draws from the same generator)."""

    def __init__(self, batches: SceneBatches):
        self.batches, self.generator = batches, batches.generator

    def __iter__(self):
        for x, y in self.batches:
            yield x.double(), y
