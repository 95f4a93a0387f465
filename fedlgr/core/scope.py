"""What a client exchanges with the server: the aggregation scope x the strategy's filter.

Scope ``full`` shares the whole model; scope ``root`` (FedRoot, the paper's Fig. 1) shares
the tensors of the root only - the top never leaves the client. Within the scope the
strategy may keep more local (FedBN: BatchNorm parameters and statistics). Only floating
point tensors travel: BatchNorm's ``num_batches_tracked`` counters stay with each client.
Under client-level DP (``federated.dp``) BatchNorm's running statistics stay too: they are
the clients' data's statistics, and released with noise they broke the model (a variance
pushed to 0 scales its layer's output without bound; docs/privacy.md).
"""

from __future__ import annotations

import torch
from torch import nn

from fedlgr.core.models.scholar import build_scholar
from fedlgr.core.state import seeded_global_rng
from fedlgr.core.strategies import Strategy

SCOPE_PREFIX = {"full": "", "root": "root."}


def batchnorm_keys(model: nn.Module) -> set[str]:
    """State-dict keys of every BatchNorm layer's parameters and buffers."""
    keys = set()
    for name, module in model.named_modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm):
            prefix = f"{name}." if name else ""
            keys.update(prefix + k for k in module.state_dict())
    return keys


def shared_keys(model: nn.Module, scope: str, strategy: Strategy) -> list[str]:
    """The state-dict keys a client uploads and downloads, in state-dict order."""
    prefix = SCOPE_PREFIX[scope]
    bn = batchnorm_keys(model)
    private = strategy.config.dp.enabled  # running statistics stay on the clients
    parameters = parameter_keys(model)
    return [
        key
        for key, value in model.state_dict().items()
        if key.startswith(prefix)
        and torch.is_floating_point(value)
        and strategy.shares(key, key in bn)
        and not (private and key in bn and key not in parameters)
    ]


def parameter_keys(model: nn.Module) -> set[str]:
    """State-dict keys that are trainable parameters (not buffers)."""
    return {name for name, _ in model.named_parameters()}


def initial_scholar(config) -> nn.Module:
    """The run's initial model: the same in every process, on every client's machine and on
    the server (seeded by ``config.seed``; the global RNG is left as it was)."""
    with seeded_global_rng(config.seed):
        return build_scholar(config)
