"""Faults simulated in one process or in Fabric's processes (``federated.faults.*``).

- **Drop-outs**: each round, each chosen client drops out with probability ``dropout``: it
  neither trains nor uploads (as a robot that is offline for the round), keeps its state,
  and is still scored, as a client the strategy did not choose; ``faults/dropped`` counts
  them. Drawn from the run's seed and the round, the same in every process and after a
  resume.
- **Stragglers**: each round, each chosen client that did not drop out is late with
  probability ``straggler``: it trains (its private state moves on, its costs count) but its
  upload arrives after the round's deadline and is dropped, as Flower drops a reply that
  comes after ``timeout`` - never used stale in a later round. ``faults/late`` counts them.
- **Byzantine clients**: ``byzantine`` clients, drawn once from the run's seed, train as
  the others but send, instead of their tensors ``w`` (global ``g``): ``sign_flip``
  ``g - (w - g)`` (the update reversed), ``noise`` ``w + N(0, noise^2)`` on every value
  (seeded by the round and the client), or ``scale`` ``g + scale (w - g)``; or, with
  ``labels``, train honestly on poisoned data - every training scene rated ``label`` for
  every action - and send what that gives. Integer tensors (BatchNorm's counter) are sent
  as they are. What the server makes of them is the
  strategy's and its checks' business (:mod:`fedlgr.core.server.screen`).

Flower's robots are real: nothing is simulated there.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from fedlgr.core.messages import TrainRes, Weights

STREAM = 0xFA017  # the faults' own random stream, apart from the clients' draw
LATE = 0x1A7E  # the stragglers' draw, apart from the drop-outs'


class Faults:
    def __init__(self, settings, clients: int, seed: int):
        self.settings, self.seed = settings, seed
        rng = np.random.default_rng([seed, STREAM])
        picked = rng.choice(clients, size=settings.byzantine, replace=False)
        self.byzantine = frozenset(int(c) for c in picked)

    def dropped(self, round_: int, chosen: list[int]) -> list[int]:
        """The chosen clients that drop out of round ``round_``."""
        if not self.settings.dropout:
            return []
        draws = np.random.default_rng([self.seed, STREAM, round_]).random(len(chosen))
        return [c for c, u in zip(chosen, draws, strict=True) if u < self.settings.dropout]

    def late(self, round_: int, training: list[int]) -> list[int]:
        """The ``training`` clients whose upload of round ``round_`` comes after its deadline."""
        if not self.settings.straggler:
            return []
        draws = np.random.default_rng([self.seed, STREAM, LATE, round_]).random(len(training))
        return [c for c, u in zip(training, draws, strict=True) if u < self.settings.straggler]

    @property
    def poisoned(self) -> frozenset[int]:
        """The clients that train on poisoned labels (``attack=labels``)."""
        return self.byzantine if self.settings.attack == "labels" else frozenset()

    def what(self, round_: int, chosen: list[int]) -> dict[int, str]:
        """Which of the round's ``chosen`` clients failed how (before the server's checks):
        ``dropped``, ``late``, ``byzantine (attack)``."""
        dropped = self.dropped(round_, chosen)
        training = [c for c in chosen if c not in dropped]
        out = {c: "dropped" for c in dropped}
        out |= {c: "late" for c in self.late(round_, training)}
        attack = self.settings.attack
        for c in training:
            if c in self.byzantine:
                out[c] = f"byzantine ({attack})" + (", late" if out.get(c) == "late" else "")
        return out

    def sent(self, result: TrainRes, shared: Weights, round_: int) -> TrainRes:
        """What client ``result.client`` sends the server in round ``round_``: its upload,
        or a Byzantine client's altered one."""
        if result.client not in self.byzantine or self.settings.attack == "labels":
            return result
        attack = self.settings.attack
        seeds = np.random.SeedSequence([self.seed, STREAM, round_, result.client])
        g = torch.Generator().manual_seed(int(seeds.generate_state(1, np.uint64)[0] >> 1))
        weights = {}
        for key, w in result.weights.items():
            if not w.is_floating_point():
                weights[key] = w
            elif attack == "sign_flip":
                weights[key] = 2 * shared[key] - w
            elif attack == "scale":
                weights[key] = shared[key] + self.settings.scale * (w - shared[key])
            else:  # noise
                noise = torch.randn(w.shape, generator=g, dtype=w.dtype)
                weights[key] = w + self.settings.noise * noise.to(w.device)
        return dataclasses.replace(result, weights=weights)


def fault_counts(faults: dict[int, str], settings) -> dict[str, float]:
    """A round's ``faults/dropped`` and ``faults/late``, each where ``settings`` simulates it."""
    counts = {}
    if settings.dropout:
        counts["faults/dropped"] = float(sum(f == "dropped" for f in faults.values()))
    if settings.straggler:
        counts["faults/late"] = float(sum(f.endswith("late") for f in faults.values()))
    return counts
