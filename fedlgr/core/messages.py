"""What the server and the clients say to each other in one round: the only boundary
between the two sides, the same in every runtime.

A round is two exchanges. **Train**: the strategy chooses the round's clients; the server
sends each its plan (with the global tensors where the client does not already hold
them, and the strategy's payload for that client, e.g. SCAFFOLD's control variate); each
trains and uploads its shared tensors, its sample count, its plugins' payload and its
figures (training loss, costs) by name. **Evaluate**: the server sends the new global
tensors; every client - chosen or not - takes them, ends the task at a task's last round
(importance, memories, generators) and reports its scores on its test scenes by name.

In the in-process runtime (``fedlgr.core.in_process``) these objects are passed by
reference in one process; across Fabric's processes the same objects are built in every
process and the server side's sums travel as one ``all_reduce``; in the Flower runtime
(``fedlgr.shell.deploy.flower``) they are encoded into Flower messages.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from fedlgr.core.metrics import Figures
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
    # What the strategy sends this client besides the weights (SCAFFOLD: the server's
    # control variate), read by the strategy's plugin on the client.
    payload: Weights = field(default_factory=dict)


@dataclass
class TrainRes:
    client: int
    weights: Weights  # the shared tensors, nothing else (see ``check_shared``)
    n_samples: int  # aggregation weight: the client's training scenes of the task
    # train/loss, train/samples and the training's costs (cost/*), by key
    figures: Figures = field(default_factory=dict)
    # What the strategy's plugins send the server besides the weights (SCAFFOLD: the
    # change of the client's control variate).
    payload: Weights = field(default_factory=dict)


@dataclass
class EvaluateIns:
    plan: RoundPlan
    weights: Weights  # the new global tensors
    clients: tuple[int, ...] | None = None  # the clients that score them (None: all)


@dataclass
class EvaluateRes:
    client: int
    # Its scores (test/*, task/*), its plugins' figures (<plugin>/<name>) and, at a task's
    # end, what ending the task cost (cost/*), by key.
    figures: Figures = field(default_factory=dict)


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
