"""The aggregation strategy interface, and FedAvg (McMahan et al. 2017).

A strategy decides who trains and what travels, and how the server aggregates (Flower's
``configure_fit`` / ``aggregate_fit``): which clients train in a round (``select``: all of
them, or a seeded ``federated.fraction`` of them), what each chosen client is sent besides
the global tensors (``payload``: per-client state such as SCAFFOLD's control variate),
which of the scope's tensors are exchanged (``shares``), what each client adds to its
local training (``client_plugins``), how the server aggregates the clients' uploads
(their sample-weighted mean, from sums that processes add up; or, for a robust statistic
such as a median, ``combine`` over every upload), turns the aggregate into the next
global weights (``server_update``) and takes in what their plugins sent
(``take_payloads``). What is shared at all - the whole model or the root
only - is the orthogonal *scope* (``fedlgr.core.scope``): FedRoot x every strategy are
combinations, not a class each. Subclasses override only what differs (Flower's
``Strategy``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from fedlgr.core.client.plugins import ClientPlugin
from fedlgr.core.messages import Weights

if TYPE_CHECKING:
    from fedlgr.core.settings import FederatedConfig


def participants(
    round_: int, clients: int, fraction: float, seed: int, poisson: bool = False
) -> list[int]:
    """The clients that train in round ``round_``: all of them at ``fraction`` 1, else
    ``max(1, round(fraction * clients))`` drawn without replacement from the run's ``seed``
    and the round (so a resumed run, and every runtime, draws the same), sorted. With
    ``poisson`` (client-level DP) each client is drawn on its own with probability
    ``fraction``: a round may have none, or all."""
    if fraction >= 1.0:
        return list(range(clients))
    rng = np.random.default_rng([seed, round_, 0x5E1EC7])
    if poisson:
        return [int(c) for c in np.flatnonzero(rng.random(clients) < fraction)]
    k = max(1, round(fraction * clients))
    return sorted(int(c) for c in rng.choice(clients, size=k, replace=False))


class Strategy:
    """FedAvg: every tensor in scope is shared; the new global is the mean of the
    clients' tensors weighted by their number of training samples."""

    def __init__(self, config: FederatedConfig):
        self.config = config
        self.settings = config.settings  # federated.<strategy>: FedProx's mu, FedOpt's lr, ...

    def bind(self, shared: list[str], parameters: set[str], initial: Weights | None = None) -> None:
        """Called once by the server with the model's shared tensors' names, those that
        are trainable parameters (not BatchNorm statistics: a server optimiser steps the
        parameters only, :class:`ServerOptimizer`) and the initial global tensors."""

    # ------------------------------------------------------------------ who trains

    def select(self, round_: int, clients: int, seed: int) -> list[int]:
        """The clients that train in round ``round_`` of ``clients`` (``federated.fraction``,
        drawn from the run's ``seed``: :func:`participants`); the others keep their state
        and are still evaluated; under client-level DP, Poisson sampling)."""
        poisson = self.config.dp.enabled  # what the accountant assumes
        return participants(round_, clients, self.config.fraction, seed, poisson)

    def payload(self, client: int) -> Weights:
        """What a chosen client is sent besides the global tensors this round (read by this
        strategy's plugin on the client); nothing by default."""
        return {}

    # ------------------------------------------------------------------ what is shared

    def shares(self, key: str, batchnorm: bool) -> bool:
        """Is this in-scope tensor exchanged? ``batchnorm``: it belongs to a BatchNorm layer."""
        return True

    # The classes of what ``client_plugins`` returns (the server reads what they measure).
    client_plugin_types: tuple[type[ClientPlugin], ...] = ()

    def client_plugins(self, client: int) -> list[ClientPlugin]:
        """What this strategy adds to a client's local training (one list per client)."""
        return []

    # ------------------------------------------------------------------ aggregation

    # Whether the aggregate is a statistic of the uploads themselves (a median, a trimmed
    # mean, Krum's choice) rather than their weighted sum: the runtimes then gather every
    # upload of the round and call ``combine``.
    needs_uploads = False

    # The headline of robots' scores (fedlgr.core.records.headline), which the server cannot
    # check: a robust strategy's statistic, that as many liars as it withstands cannot move
    # far, and the mean for the others.
    scores_statistic = "mean"

    def combine(self, uploads: list[tuple[int, Weights]]) -> Weights:
        """The aggregate of the round's uploads, ``(n_samples, tensors)`` in client order,
        as float64 tensors (called where ``needs_uploads``; FedAvg's sample-weighted mean
        is taken from sums instead)."""
        raise NotImplementedError

    def payload_refusal(
        self, result, shared: Weights, steps: int, learning_rates: dict[str, float]
    ) -> str | None:
        """Why what ``result``'s plugins sent cannot be what they compute from its own upload
        and the global tensors ``shared`` (``steps``: the fewest local steps its sample count
        trains; ``learning_rates``: each parameter's local one), or None; nothing to check
        by default."""
        return None

    def server_update(self, global_weights: Weights, mean: Weights) -> Weights:
        """The next global weights from the clients' sample-weighted mean."""
        return mean

    def payload_template(self) -> Weights:
        """Zeros shaped like what a chosen client's plugins send (``payload``), so that
        processes can add their sums up; nothing by default."""
        return {}

    def take_payloads(self, sums: Weights, senders: int, clients: int) -> None:
        """What the round's clients' plugins sent, summed over the ``senders`` clients that
        trained (of ``clients``); nothing is sent by default."""

    def state_dict(self) -> dict:
        """Server-side state (e.g. FedOpt's moments), for checkpoints."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore what ``state_dict`` returned."""


FedAvg = Strategy


class ServerOptimizer(Strategy):
    """A strategy whose server update is an optimiser step on the shared parameters, from
    the clients' mean update Delta = mean - global (FedOpt, FedAvgM); tensors that are not
    parameters (BatchNorm running statistics) take the plain mean, as in FedAvg."""

    def __init__(self, config: FederatedConfig):
        super().__init__(config)
        self.trainable: set[str] = set()  # the shared parameters (bind)

    def bind(self, shared: list[str], parameters: set[str], initial: Weights | None = None) -> None:
        self.trainable = parameters & set(shared)

    def server_update(self, global_weights: Weights, mean: Weights) -> Weights:
        return {
            key: self.step(key, global_weights[key], avg - global_weights[key])
            if key in self.trainable
            else avg
            for key, avg in mean.items()
        }

    def step(self, key: str, weight: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        """The next global value of parameter ``key`` from its value and its mean update."""
        raise NotImplementedError
