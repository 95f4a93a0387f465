"""What a runtime supplies to a run: its rounds.

A runtime - the in-process one (:class:`fedlgr.core.in_process.Orchestrator`: clients in
this process or in Fabric's processes) or the Flower runtime (``FlowerRounds`` in
``fedlgr.shell.deploy.flower``: each client on its own machine) - runs each round
of the schedule and holds the state the next round depends on; the run around it
(tracking, checkpoints, resume, the failure record: :mod:`fedlgr.shell.run`) asks for
nothing more.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from fedlgr.core.messages import RoundPlan
from fedlgr.core.records import RoundLog

EpochProgress = Callable[[int, int], None]  # ``progress(client, epoch)`` after a local epoch


class Rounds(Protocol):
    """A runtime's rounds."""

    @property
    def local_clients(self) -> int:
        """How many clients train in this process (0: none do: the Flower runtime's train on
        their own machines); the round's progress bar counts their local epochs."""
        ...

    def run_round(self, plan: RoundPlan, progress: EpochProgress | None = None) -> RoundLog:
        """Train, aggregate and evaluate the round ``plan``; its log (the same in every
        process). ``progress(client, epoch)`` after each local epoch of this process's
        clients."""
        ...

    def state_dict(self) -> dict:
        """Everything the next round depends on - the server's state, every client's
        that lives in this runtime, the random generators - whole in the process that
        writes checkpoints (rank 0); every process calls it."""
        ...

    def load_state_dict(self, state: dict) -> None:
        """Restore what ``state_dict`` returned (every process, its own part)."""
        ...
