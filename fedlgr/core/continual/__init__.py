"""Continual-learning methods as client plug-ins (docs/fedlgr.md), by ``continual.method``.

Each method is one module here (``ewc.py``, ``si.py``, ``lgr.py`` for FedLGR's latent
generative replay, ...), registered in :data:`fedlgr.core.methods.CONTINUAL` with its settings
(``continual.<method>.*``). They plug into every client's local training, so they compose
with every strategy and scope; their state is per client and strictly local.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from fedlgr.core.client.plugins import ClientPlugin
from fedlgr.core.continual.batchnorm import FrozenRootStatistics
from fedlgr.core.methods import CONTINUAL

if TYPE_CHECKING:
    from fedlgr.core.settings import ContinualConfig


def _seed(seed: int, client: int) -> int:
    return int(np.random.SeedSequence([seed, client, 7]).generate_state(1)[0])


def continual_plugin_types(config: ContinualConfig) -> list[type[ClientPlugin]]:
    """The class of the plugin ``continual.method`` adds (none for ``none``)."""
    method = CONTINUAL[config.method]
    return [] if method.target is None else [method.load()]


def continual_plugins(config: ContinualConfig, client: int, seed: int) -> list[ClientPlugin]:
    """The plugins ``continual.method`` adds to one client's training (none for ``none``),
    after the root's frozen BatchNorm statistics where the method asks for them."""
    settings = config.settings
    freeze = getattr(settings, "freeze_root_bn", config.freeze_root_bn)
    plugins: list[ClientPlugin] = [FrozenRootStatistics()] if freeze and config.tasks else []
    for cls in continual_plugin_types(config):
        plugins.append(cls.from_settings(settings, config, _seed(seed, client)))
    return plugins


__all__ = ["continual_plugin_types", "continual_plugins"]
