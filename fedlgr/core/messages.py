"""What the server and the clients say to each other in one round: the only boundary
between the two sides, the same in every runtime.

A round is two exchanges. **Train**: the server sends the round's plan (and the global
tensors, where the client does not already hold them); each client trains and uploads
its shared tensors, its sample count and what the training cost. **Evaluate**: the server
sends the new global tensors; each client takes them, ends the task at a task's last
round (importance, memories, generators) and reports its scores on its test scenes.

In one process (``fedlgr.core.in_process``) these objects are passed by
reference; in Fabric's multi-process mode the same objects are built in every process
and the server's sums travel as one ``all_reduce``; on Flower
(``fedlgr.shell.deploy.flower``) they are encoded into Flower messages.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from fedlgr.core.meters.costs import Usage
from fedlgr.errors import FedlgrError

Weights = dict[str, torch.Tensor]


@dataclass(frozen=True)
class RoundPlan:
    """The server's instructions for one round: one step of the run's schedule
    (:func:`fedlgr.core.schedule.schedule`)."""

    round: int  # 1-based, over the whole run
    task: int = 0  # position of the task in the schedule
    first_of_task: bool = False
    last_of_task: bool = False


@dataclass
class TrainIns:
    plan: RoundPlan
    weights: Weights | None = None  # None: the client holds the current global tensors


@dataclass
class TrainRes:
    client: int
    weights: Weights  # the shared tensors, nothing else (see ``check_shared``)
    n_samples: int  # aggregation weight: the client's training scenes of the task
    samples: int  # samples trained on, all epochs, rehearsal included
    loss: float  # mean task loss over the round
    usage: Usage = field(default_factory=Usage)


@dataclass
class EvaluateIns:
    plan: RoundPlan
    weights: Weights  # the new global tensors


@dataclass
class EvaluateRes:
    client: int
    scores: list[float]  # the score fields, in ``fedlgr.core.fields`` order
    figures: dict[str, float] = field(default_factory=dict)  # plugins' task-end figures
    usage: Usage | None = None  # the end of the task's cost, when there is one


def nbytes(weights: Weights) -> int:
    """Bytes of the tensors as they travel (their element size times their count)."""
    return sum(t.numel() * t.element_size() for t in weights.values())


def check_shared(weights: Weights, keys: list[str], who: str, prefix: str = "") -> None:
    """Refuse any tensor outside the shared ones, and (independently of how ``keys`` were
    made) any tensor whose name lacks the scope's ``prefix`` (``root.``: FedRoot's
    premise): the top, the generator and the CL state never leave a client."""
    outside = sorted(k for k in weights if not k.startswith(prefix))
    if outside:
        raise FedlgrError(
            f"{who}: {outside[:5]} outside the shared scope ({prefix!r} tensors only); "
            "nothing private may leave a client"
        )
    extra = sorted(set(weights) - set(keys))
    missing = sorted(set(keys) - set(weights))
    if extra or missing:
        raise FedlgrError(
            f"{who}: the tensors exchanged must be exactly the shared ones "
            f"(not shared: {extra[:5]}{'...' if len(extra) > 5 else ''}; "
            f"missing: {missing[:5]}{'...' if len(missing) > 5 else ''})"
        )
