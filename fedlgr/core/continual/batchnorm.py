"""BatchNorm statistics in continual learning: freeze the root's, keep modes intact.

CL methods protect weights (EWC, SI, MAS penalise moving them; FedLGR trains the root at a
small lr_R), but a BatchNorm layer in training mode also moves its running mean and
variance towards every batch it sees, at no learning rate at all. In a later task those
statistics drift to the new task's data and the features of old scenes change with them:
LGR's premise of a static latent space (the paper, Sec. III-B a) breaks. Freezing them
from the second task on means putting the root's BatchNorm layers in eval mode during
local training: they normalise with the statistics learnt so far and no longer update them
(``num_batches_tracked`` included), so the root computes in training what it computes in
evaluation.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from torch import nn

from fedlgr.core.client.plugins import ClientPlugin, LocalContext


def batchnorm_layers(module: nn.Module) -> list[nn.Module]:
    return [m for m in module.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]


def freeze_batchnorm_statistics(module: nn.Module) -> None:
    """Put every BatchNorm layer of ``module`` in eval mode (until the next ``.train()``)."""
    for layer in batchnorm_layers(module):
        layer.eval()


@contextlib.contextmanager
def eval_mode(module: nn.Module) -> Iterator[nn.Module]:
    """``module`` in eval mode, then every sub-module's own mode restored (``.train(was)``
    on the whole would unfreeze frozen BatchNorm layers)."""
    modes = [(m, m.training) for m in module.modules()]
    module.eval()
    try:
        yield module
    finally:
        for m, was in modes:
            m.training = was


class FrozenRootStatistics(ClientPlugin):
    """From the second task of the schedule on, the root's BatchNorm statistics stay as
    they were at the end of the first (``continual.freeze_root_bn``; FedLGR:
    ``continual.lgr.freeze_root_bn``)."""

    name = "freeze_root_bn"

    def on_round_start(self, ctx: LocalContext) -> None:
        if ctx.task > 0:
            freeze_batchnorm_statistics(ctx.model.root)
