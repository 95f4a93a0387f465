"""The server side of a federation: the global tensors, the strategy's choice of clients,
aggregation, the strategy's server step, and the round's record.

:class:`ServerSide` needs no data and no client: it builds the run's initial model to
know the shared tensors, asks the strategy which clients train in a round and what each
is sent (:meth:`train_ins`), aggregates what they upload (sample-weighted mean, in
float64, then ``Strategy.server_update``; their plugins' payloads summed for
``Strategy.take_payloads``) - in one process, or in each of several that hold a share of
the uploads (a :class:`Collective`) - and turns the clients' figures into the round's
:class:`RoundLog`, a row per client: a client that did not report (a robot that dropped
out) has none and is named in ``RoundLog.missing``.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from fedlgr.core.faults import fault_counts
from fedlgr.core.messages import RoundPlan, TrainIns, TrainRes, Weights, nbytes
from fedlgr.core.methods import plugin_metrics
from fedlgr.core.metrics import Figures, combine, round_keys
from fedlgr.core.privacy import UNCLIPPED, Privacy
from fedlgr.core.records import RoundLog, table
from fedlgr.core.schedule import ALL
from fedlgr.core.scope import initial_scholar, parameter_keys, shared_keys
from fedlgr.core.server.aggregate import finish_mean, weighted_sum
from fedlgr.core.server.screen import (
    capped_counts,
    digest,
    oversized,
    payload_norm,
    refusal,
    update_norm,
)
from fedlgr.core.state import to_device
from fedlgr.core.strategies import build_strategy

if TYPE_CHECKING:
    from fedlgr.core.messages import EvaluateRes
    from fedlgr.core.settings import ExperimentConfig


class Collective:
    """The processes that each hold a share of a round's uploads (Fabric's), each making the
    same calls: every process's ``part`` in rank order (tensors on this process's device),
    the sum of each one's ``flat``. This base is one process alone: the identity."""

    processes = 1

    def all_gather(self, part: Any) -> list[Any]:
        return [part]

    def all_reduce_sum(self, flat: torch.Tensor) -> torch.Tensor:
        return flat


ALONE = Collective()


class ServerSide:
    """``robots``: the clients are robots (a real deployment): client-level DP's noise comes
    from the operating system, not from the run's seed (:mod:`fedlgr.core.privacy`), and
    as the server cannot tell an honest robot's scores from a liar's, their headline is the
    strategy's robust statistic (``Strategy.scores_statistic``: a median for FedMedian); in
    one process every score is fedlgr's own, the simulated attackers' kept apart, and the
    headline is the others' mean."""

    def __init__(self, config: ExperimentConfig, robots: bool = False):
        cfg = config
        self.config = config
        self.tasks = list(cfg.continual.tasks) or [ALL]
        self.strategy = build_strategy(cfg.federated)
        initial = initial_scholar(cfg)
        self.keys = shared_keys(initial, cfg.federated.scope, self.strategy)
        state = initial.state_dict()
        self.global_weights: Weights = {k: state[k].detach().clone() for k in self.keys}
        self.strategy.bind(self.keys, parameter_keys(initial), self.global_weights)
        # each parameter's local learning rate (its optimiser group's, as every client has
        # it): what a strategy's payload is computed with (SCAFFOLD's option II)
        rates = {
            id(p): g["lr"] for g in initial.configure_optimizers().param_groups for p in g["params"]
        }
        self.learning_rates = {k: rates[id(p)] for k, p in initial.named_parameters()}
        # the fingerprints of every upload each client sent (screen.digest): a replay is stale
        self.seen: dict[int, set[str]] = {}
        self.initial_bytes = nbytes(self.global_weights)
        # What the method's client plugins measure (every client has the same kinds).
        self.plugin_keys = plugin_metrics(cfg.federated.strategy, cfg.continual.method)
        self.round_keys = round_keys(self.tasks, self.plugin_keys)  # a round's columns
        # this round's refusals: client -> what and why ("upload: ...", "scores: ...")
        self.refused: dict[int, str] = {}
        # this round's sample counts capped (federated.count_cap): client -> what
        self.capped: dict[int, str] = {}
        # federated.dp: clipped updates, noise on their sum, the accountant's epsilon
        dp = cfg.federated.dp.enabled
        self.privacy = Privacy(cfg, robots) if dp else None
        self.statistic = self.strategy.scores_statistic if robots else "mean"

    def to(self, device: torch.device) -> ServerSide:
        self.global_weights = {k: v.to(device) for k, v in self.global_weights.items()}
        return self

    # ------------------------------------------------------------------ who trains

    def chosen(self, plan: RoundPlan) -> list[int]:
        """The clients the strategy chooses to train in round ``plan`` (seeded)."""
        return self.strategy.select(plan.round, self.config.data.clients, self.config.seed)

    def train_ins(self, plan: RoundPlan, client: int, holds_global: bool = True) -> TrainIns:
        """A chosen client's training message: the plan, the strategy's payload for it,
        and the global tensors where the client does not hold them yet (round 1, or a
        robot that missed the last round)."""
        weights = None if holds_global else self.global_weights
        return TrainIns(plan, weights, self.strategy.payload(client))

    def bytes_down(self, round_: int, trained: bool = True) -> int:
        """What a client that took part in every round downloads in round ``round_``: the
        new global tensors, and in round 1, where it trained, the initial ones too."""
        initial = self.initial_bytes if round_ == 1 and trained else 0
        return nbytes(self.global_weights) + initial

    # ------------------------------------------------------------------ what is taken

    def refusals(
        self, results: Iterable[TrainRes], capacity: Mapping[int, int] | None = None
    ) -> dict[int, str]:
        """The uploads that cannot be aggregated, client -> why (:mod:`.screen`):
        ``capacity``, where the server knows it, bounds each client's sample count."""
        results = list(results)
        bound, payload = capacity or {}, self.strategy.payload_template()
        found = {
            r.client: refusal(r, self.global_weights, bound.get(r.client), payload) for r in results
        }
        counts = Counter(r.client for r in results)
        for r in results:  # well formed: is its payload its update's, is it new?
            if found[r.client] is None and counts[r.client] == 1:
                found[r.client] = self.stale(r) or self.strategy.payload_refusal(
                    r, self.global_weights, self.fewest_steps(r.n_samples), self.learning_rates
                )
        for client in counts:
            if counts[client] > 1:  # which one would be its? neither is taken
                found[client] = f"{counts[client]} uploads in one round"
            elif not (
                isinstance(client, int | np.integer) and 0 <= client < self.config.data.clients
            ):
                found[client] = f"no client {client!r} in data.clients={self.config.data.clients}"
        return {client: why for client, why in found.items() if why is not None}

    def stale(self, result: TrainRes) -> str | None:
        """Why the upload is a replay - identical to one its client sent before - or None; it is
        remembered either way."""
        seen = self.seen.setdefault(result.client, set())
        mark = digest(result)
        if mark in seen:
            return "stale: identical to an upload it sent before (a replay)"
        seen.add(mark)
        return None

    def fewest_steps(self, n_samples: int) -> int:
        """The fewest local optimiser steps a client takes on ``n_samples`` scenes: every epoch
        goes over each scene at least once, in batches of ``train.batch_size`` - at most
        ``train.max_batches`` of them."""
        train = self.config.train
        batches = math.ceil(n_samples / train.batch_size)
        return train.epochs * min(batches, train.max_batches or batches)

    def update_norms(self, results: Iterable[TrainRes], refused: Mapping[int, str]) -> dict:
        """client -> the norms of its update and of its payload, for the uploads not
        ``refused``."""
        shared = self.global_weights
        return {
            r.client: (update_norm(r, shared), payload_norm(r))
            for r in results
            if r.client not in refused
        }

    def screen(self, results: list[TrainRes], refused: dict, norms: dict) -> list[TrainRes]:
        """The uploads taken: not ``refused``, nor far larger than the round's others - the
        update and the payload each (``federated.norm_ratio`` over every process's
        ``norms``); the round's refusals are kept for its record."""
        # Under DP the clip norm bounds every update; a bound drawn from the others' norms
        # would let one client decide whether another's update counts.
        ratio = 0 if self.privacy is not None else self.config.federated.norm_ratio
        updates = {c: n[0] for c, n in norms.items()}
        payloads = {c: n[1] for c, n in norms.items()} if self.strategy.payload_template() else {}
        found = refused | oversized(payloads, ratio, "payload") | oversized(updates, ratio)
        self.refused = {client: f"upload: {why}" for client, why in found.items()}
        return [r for r in results if r.client not in self.refused]

    def cap(self, results: list[TrainRes], capacity: Mapping[int, int]) -> list[TrainRes]:
        """The uploads taken, each sample count that nothing bounds (no ``capacity``: a robot
        without the roster's ``scenes``) capped at ``federated.count_cap`` times the median of
        the round's other counts; the caps are kept for the round's record. Under DP every
        update weighs 1, and so does every upload of a robust strategy (a median, Krum):
        nothing to cap."""
        unweighted = self.privacy is not None or self.strategy.needs_uploads
        ratio = 0 if unweighted else self.config.federated.count_cap
        counts = {r.client: r.n_samples for r in results}
        caps = {c: n for c, n in capped_counts(counts, ratio).items() if c not in capacity}
        for client, cap in caps.items():
            self.capped[client] = (
                f"sample count {counts[client]} capped at {cap} ({ratio:g} x the round's "
                "others' median; no roster scenes bound it)"
            )
        return [
            dataclasses.replace(r, n_samples=caps[r.client]) if r.client in caps else r
            for r in results
        ]

    # ------------------------------------------------------------------ aggregation

    def sum_template(self) -> Weights:
        """Zeros shaped like the payloads' sums (:meth:`sums`), so that processes can add
        them up: the strategy's, and under DP the sum of the clients' centred "within the
        clip norm" bits (``UNCLIPPED``: b - 1/2 each, 0 for no client)."""
        template = self.strategy.payload_template()
        if self.privacy is not None:
            like = next(iter(self.global_weights.values()))
            zero = torch.zeros((), dtype=torch.float64, device=like.device)
            template = template | {UNCLIPPED: zero}
        return template

    def sums(self, results: Iterable[TrainRes]) -> tuple[Weights, float, Weights]:
        """Sample-weighted sums of the uploads the server took (:meth:`screen`: they hold
        exactly the shared tensors; float64), the sum of the weights, and the plain sums of
        the plugins' payloads (float64). Under DP each upload's update is clipped first
        and weighs 1."""
        results = list(results)
        if self.privacy is not None:
            results = [self.privacy.clipped(r, self.global_weights) for r in results]
        sums, total = weighted_sum(((r.n_samples, r.weights) for r in results), self.keys)
        return sums, total, _payload_sums(results)

    def update(self, sums: Weights, total: float, payloads: Weights, senders: int) -> None:
        """The next global tensors from the sums of every upload of the round's
        ``senders`` clients; the strategy takes in their payloads. Under DP the sums are
        released with noise (every round, also one with no upload)."""
        if self.privacy is None:
            mean = finish_mean(sums, total, like=self.global_weights)
        else:
            payloads = {k: v.double() for k, v in self.sum_template().items()} | payloads
            mean, payloads = self.privacy.mean(sums, total, payloads, self.global_weights)
        self.global_weights = self.strategy.server_update(self.global_weights, mean)
        self.strategy.take_payloads(payloads, senders, self.config.data.clients)

    def aggregate(
        self,
        results: Iterable[TrainRes],
        capacity: Mapping[int, int] | None = None,
        refused: Mapping[int, str] | None = None,
        collective: Collective = ALONE,
    ) -> None:
        """The next global tensors from every upload of the round that the server takes
        (none taken: no change, but under DP the noise is released). ``results``: this
        process's; ``collective``: the processes with the others, each calling this.
        ``capacity``: :meth:`refusals`; ``refused``: uploads already refused (client ->
        why: a robot's that could not be read)."""
        results = list(results)
        refused = {**(refused or {}), **self.refusals(results, capacity)}
        parts = collective.all_gather((refused, self.update_norms(results, refused)))
        refused = {c: why for part, _ in parts for c, why in part.items()}
        norms = {c: norm for _, part in parts for c, norm in part.items()}
        results = self.screen(results, refused, norms)  # on every process's norms
        results = self.cap(results, capacity or {})
        senders = sum(c not in self.refused for c in norms)  # taken, in every process
        if self.strategy.needs_uploads:  # a statistic of every upload: gather them
            taken = [r for part in collective.all_gather(results) for r in part]
            if taken:
                self.combine(sorted(taken, key=lambda r: r.client), senders)
            return
        sums, total, payloads = self.sums(results)
        if collective.processes > 1:
            total = self.all_reduce(sums, total, payloads, collective)
        if total > 0 or self.privacy is not None:
            self.update(sums, total, payloads, senders)

    def all_reduce(
        self, sums: Weights, total: float, payloads: Weights, collective: Collective
    ) -> float:
        """:meth:`sums`' results summed over the processes in one collective, ``sums`` and
        ``payloads`` in place (zeros for a key a process has no sum of: none of its uploads
        was taken); returns the summed ``total``."""
        template = self.sum_template()
        layout = [(sums, k, self.global_weights[k]) for k in self.keys]
        layout += [(payloads, k, template[k]) for k in sorted(template)]
        parts = [
            out.get(k, torch.zeros_like(t, dtype=torch.float64)).flatten().double()
            for out, k, t in layout
        ]
        flat = collective.all_reduce_sum(torch.cat([*parts, parts[0].new_tensor([total])]))
        sizes = [t.numel() for *_, t in layout]
        for (out, k, t), part in zip(layout, flat[:-1].split(sizes), strict=True):
            out[k] = part.view(t.shape)
        return float(flat[-1])

    def combine(self, results: list[TrainRes], senders: int) -> None:
        """The next global tensors from the strategy's statistic of the uploads
        (``Strategy.combine``: a median, Krum, ...), for strategies that need them all;
        ``results``: the uploads the server took (:meth:`screen`)."""
        uploads = [(r.n_samples, {k: r.weights[k] for k in self.keys}) for r in results]
        combined = self.strategy.combine(uploads)
        like = self.global_weights
        aggregate = {k: combined[k].to(like[k].dtype) for k in self.keys}
        self.global_weights = self.strategy.server_update(self.global_weights, aggregate)
        self.strategy.take_payloads(_payload_sums(results), senders, self.config.data.clients)

    # ------------------------------------------------------------------ the record

    def row(
        self, trained: TrainRes | None, evaluated: EvaluateRes, bytes_up: int, bytes_down: int
    ) -> Figures:
        """One client's figures in the round: its training's (none where it was not
        chosen), its scores and task end's, the bytes it moved."""
        figures = (
            evaluated.figures if trained is None else combine(trained.figures, evaluated.figures)
        )
        up = {} if trained is None else {"cost/bytes_up": float(bytes_up)}
        return figures | up | {"cost/bytes_down": float(bytes_down)}

    def table(self, rows: Mapping[int, Figures], fill: float = math.nan) -> np.ndarray:
        """All clients' rows by the round's keys (clients x keys, float64): ``fill`` for
        the clients that have none here (0 where processes add their tables up)."""
        return table(self.round_keys, rows, self.config.data.clients, fill)

    def round_log(
        self,
        plan: RoundPlan,
        table_: np.ndarray,
        seconds: float,
        missing: tuple[int, ...] = (),
        participants: list[int] | None = None,
        served: tuple[dict[str, float], dict[str, float]] = ({}, {}),
        faults: Mapping[int, str] | None = None,
        names: Mapping[int, str] | None = None,
        bad_scores: Mapping[int, str] | None = None,
        byzantine: Iterable[int] = (),
    ) -> RoundLog:
        """The round's record; ``participants`` (the clients that trained) is kept where the
        strategy chose fewer than all. ``served``: the server's figures and the initial
        model's scores (:func:`~fedlgr.core.server.evaluate.serve_round`), to which the
        counts of the simulated ``faults`` (client -> what) are added; ``names``: client ->
        its robot; ``bad_scores``: the clients whose scores were refused, client -> why;
        ``byzantine``: the simulated attackers, whose scores are kept apart."""
        clients = self.config.data.clients
        chosen = None if participants is None or len(participants) == clients else participants
        refused, self.refused = self.refused, {}
        capped, self.capped = self.capped, {}
        for client, why in (bad_scores or {}).items():  # their rows are left out
            said = refused.get(client)
            refused[client] = f"{said}; scores: {why}" if said else f"scores: {why}"
        faults = dict(faults or {})
        return RoundLog(
            plan.round,
            self.tasks[plan.task],
            self.round_keys,
            table_,
            seconds,
            missing,
            served[0] | fault_counts(faults, self.config.federated.faults),
            dict(served[1]),
            participants=None if chosen is None else tuple(chosen),
            refused=refused,
            faults=faults,
            names=dict(names or {}),
            statistic=self.statistic,
            byzantine=tuple(sorted(byzantine)),
            capped=capped,
        )

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict:
        state = {"global": self.global_weights, "strategy": self.strategy.state_dict()}
        state["seen"] = {c: sorted(marks) for c, marks in self.seen.items()}
        if self.privacy is not None:
            state["privacy"] = self.privacy.state_dict()
        return state

    def load_state_dict(self, state: dict, device: torch.device | str) -> None:
        self.global_weights = {k: v.to(device) for k, v in state["global"].items()}
        self.strategy.load_state_dict(to_device(state["strategy"], device))
        self.seen = {int(c): set(marks) for c, marks in state.get("seen", {}).items()}
        if self.privacy is not None:
            self.privacy.load_state_dict(state["privacy"])


def _payload_sums(results: list[TrainRes]) -> Weights:
    """The plain sums of what the uploads' plugins sent (float64), by key."""
    keys = sorted({k for r in results for k in r.payload})
    return weighted_sum(((1, r.payload) for r in results), keys)[0]
