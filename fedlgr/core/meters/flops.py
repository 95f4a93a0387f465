"""The floating-point operations of a training step, counted from shapes (``cost/gflops``).

torch's ``FlopCounterMode`` counts each operator with a formula of its shapes: a
multiply-add is 2 operations, a bias add and a reduction count nothing. Its formula for a
convolution's backward pass (``aten.convolution_backward``, torch 2.15) counts the weight
gradient as a convolution of the transposed input and output gradient, and those
transposed shapes lose the division by ``groups`` (pytorch/pytorch PR #183405): a depthwise
convolution's weight gradient is counted ``channels`` times over, and MobileNetV2's
training about 6x over. :func:`flop_counter` is a ``FlopCounterMode`` with a formula of its
own for that one operator - a mapping of this counter only, so nothing else in the process
changes - and torch's formulas for every other operator.

The corrected count: a convolution (grouped, transposed or not) does one multiply-add per
weight element and sliding position and sample, ``N x numel(weight) x prod(positions)``,
where the positions are the output's for a convolution and the input's for a transposed
one (``weight`` holds ``in/groups`` or ``out/groups`` channels, which is where the groups
come in). The input gradient and the weight gradient each do exactly those multiply-adds
again - every product of the forward pass is one term of each - so each counts as much
as the forward pass, and the bias gradient (a sum) counts nothing, as the bias does
forward. For ``groups=1`` this is torch's own count.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch.utils.flop_counter import FlopCounterMode

aten = torch.ops.aten


def conv_flops(
    x_shape: Sequence[int], w_shape: Sequence[int], out_shape: Sequence[int], transposed: bool
) -> int:
    """The operations of a convolution's forward pass: 2 per multiply-add, one multiply-add
    per weight element, sample and position the kernel slides over (the output's
    positions; a transposed convolution slides over its input's)."""
    positions = (x_shape if transposed else out_shape)[2:]
    return 2 * x_shape[0] * math.prod(w_shape) * math.prod(positions)


def conv_backward_flops(
    grad_out_shape: Sequence[int],
    x_shape: Sequence[int],
    w_shape: Sequence[int],
    _bias: object,
    _stride: object,
    _padding: object,
    _dilation: object,
    transposed: bool,
    _output_padding: object,
    _groups: int,
    output_mask: Sequence[bool],
    out_shape: object = None,
    **kwargs: object,
) -> int:
    """``aten.convolution_backward``'s operations (its arguments, tensors as shapes, as
    ``FlopCounterMode`` passes them): the forward pass's count once for the input gradient
    and once for the weight gradient, each where ``output_mask`` asks for it; the bias
    gradient (``output_mask[2]``) is a sum and counts nothing."""
    forward = conv_flops(x_shape, w_shape, grad_out_shape, transposed)
    return forward * (int(bool(output_mask[0])) + int(bool(output_mask[1])))


FORMULAS = {aten.convolution_backward: conv_backward_flops}


def flop_counter() -> FlopCounterMode:
    """A silent ``FlopCounterMode`` with the corrected convolution backward formula."""
    return FlopCounterMode(display=False, custom_mapping=FORMULAS)
