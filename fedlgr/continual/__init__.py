"""Continual-learning methods as client plugins (SPEC 4.2), by ``continual.method``.

Each method is one module: ``ewc.py`` (EWC, EWC-Online), ``si.py``, ``mas.py``,
``rehearsal.py`` (naive rehearsal) and ``lgr.py`` (FedLGR's latent generative replay).
They plug into every client's local training, so they compose with every strategy and
scope; their state is per client and strictly local.
"""

from __future__ import annotations

import numpy as np

from fedlgr.config import ContinualConfig
from fedlgr.continual.batchnorm import FrozenRootStatistics
from fedlgr.continual.ewc import EWC, EWCOnline
from fedlgr.continual.lgr import LatentReplay
from fedlgr.continual.mas import MAS
from fedlgr.continual.rehearsal import NaiveRehearsal
from fedlgr.continual.si import SI
from fedlgr.federated.plugins import ClientPlugin


def _seed(seed: int, client: int) -> int:
    return int(np.random.SeedSequence([seed, client, 7]).generate_state(1)[0])


def continual_plugins(config: ContinualConfig, client: int, seed: int) -> list[ClientPlugin]:
    """The plugins ``continual.method`` adds to one client's training (none for ``none``)."""
    c, s = config, _seed(seed, client)
    make = {
        "none": lambda: None,
        "ewc": lambda: EWC(c.ewc_lambda, c.ewc_fisher, c.importance_batches, s),
        "ewc_online": lambda: EWCOnline(
            c.ewc_lambda, c.ewc_gamma, c.ewc_fisher, c.importance_batches, s
        ),
        "si": lambda: SI(c.si_c, c.si_xi),
        "mas": lambda: MAS(c.mas_lambda, c.importance_batches),
        "nr": lambda: NaiveRehearsal(c.nr_memory, c.nr_replay_ratio, s),
        "lgr": lambda: LatentReplay(
            schedule=c.lgr_schedule,
            replay=c.lgr_replay,
            hidden=c.lgr_hidden,
            latent=c.lgr_latent,
            epochs=c.lgr_epochs,
            batch_size=c.lgr_batch_size,
            lr=c.lgr_lr,
            beta=c.lgr_beta,
            patience=c.lgr_patience,
            holdout=c.lgr_holdout,
            lr_root=c.lgr_lr_root,
            root_epochs=c.lgr_root_epochs,
            replay_ratio=c.lgr_replay_ratio,
            sampler=c.lgr_sampler,
            drift=c.lgr_drift,
            compensate_ridge=c.lgr_compensate_ridge,
            distill_weight=c.lgr_distill_weight,
            train_blocks=c.lgr_train_blocks,
            replay_layer=c.lgr_replay_layer,
            seed=s,
        ),
    }
    plugin = make[config.method]()
    freeze = c.lgr_freeze_root_bn if c.method == "lgr" else c.freeze_root_bn
    plugins = [FrozenRootStatistics()] if freeze and c.tasks else []
    return plugins + ([] if plugin is None else [plugin])


__all__ = [
    "EWC",
    "MAS",
    "SI",
    "EWCOnline",
    "FrozenRootStatistics",
    "LatentReplay",
    "NaiveRehearsal",
    "continual_plugins",
]
