"""NR, naive rehearsal (Hsu et al. 2018): a bounded per-client memory of past-task scenes.

At the end of each task the client's memory is re-balanced: every task seen so far keeps an
equal share of ``continual.nr.memory`` scenes (a random subset of that task's training
scenes on this client). During later tasks every batch gets ``continual.nr.replay_ratio``
memory scenes per current scene mixed in, prepared exactly like the current ones
(augmentation included).
The memory holds positions into the client's own data; it never leaves the client.
"""

from __future__ import annotations

import numpy as np
import torch

from fedlgr.core.client.plugins import ClientPlugin, LocalContext


class NaiveRehearsal(ClientPlugin):
    name = "nr"

    def __init__(self, capacity: int, replay_ratio: float, seed: int = 0):
        self.capacity, self.replay_ratio = capacity, replay_ratio
        self.rng = np.random.default_rng(seed)
        self.generator = torch.Generator().manual_seed(seed)
        self.by_task: dict[int, np.ndarray] = {}  # task position in the schedule -> scenes

    @classmethod
    def from_settings(cls, settings, continual, seed: int) -> NaiveRehearsal:
        return cls(settings.memory, settings.replay_ratio, seed)

    @property
    def memory(self) -> np.ndarray:
        """All remembered scene positions (past tasks only)."""
        parts = [self.by_task[t] for t in sorted(self.by_task)]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)

    def on_task_end(self, ctx: LocalContext) -> None:
        self.by_task[ctx.task] = ctx.batches.positions.numpy().copy()
        share = self.capacity // len(self.by_task)
        for task, positions in self.by_task.items():
            if len(positions) > share:
                self.by_task[task] = np.sort(self.rng.choice(positions, size=share, replace=False))

    def batch(self, ctx: LocalContext, x, y):
        memory = self.memory
        n = round(len(x) * self.replay_ratio)
        if len(memory) == 0 or n == 0:
            return x, y
        pick = torch.as_tensor(memory[self.rng.integers(len(memory), size=n)])
        xm, ym = ctx.batches.gather(pick, self.generator)
        return torch.cat([x, xm]), torch.cat([y, ym])

    def state_dict(self) -> dict:
        return {
            "by_task": {t: p.copy() for t, p in self.by_task.items()},
            "rng": self.rng.bit_generator.state,
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        if state:
            self.by_task = {t: p.copy() for t, p in state["by_task"].items()}
            self.rng.bit_generator.state = state["rng"]
            self.generator.set_state(state["generator"])
