"""The training schedule: which task each round trains, and where tasks begin and end.

Plain FL is one task, "all", of ``federated.rounds`` rounds; FCL trains the tasks of
``continual.tasks`` in order, ``continual.rounds_per_task`` rounds each. Each step is the
round's :class:`~fedlgr.core.messages.RoundPlan`, the plan the server sends the
clients; the round loop walks these steps: task boundaries are read from the schedule,
never worked out from round numbers.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, overload

from fedlgr.core.messages import RoundPlan
from fedlgr.core.privacy import releases_within

if TYPE_CHECKING:
    from fedlgr.core.settings import ExperimentConfig


ALL = "all"  # the single task of plain FL


class Schedule(Sequence[RoundPlan]):
    """The run's steps, made on demand: a run of a billion rounds holds no billion
    ``RoundPlan`` objects (``len`` and indexing are arithmetic). ``tasks[plan.task]`` is
    a step's task name. ``stop``: the run ends after this many rounds, whatever its tasks
    (a privacy budget spent: ``federated.dp.target_epsilon``)."""

    def __init__(
        self,
        tasks: list[str],
        rounds_per_task: int,
        task_ends: bool = True,
        stop: int | None = None,
    ):
        self.tasks, self.per_task, self.task_ends = tasks, rounds_per_task, task_ends
        self.planned = len(tasks) * rounds_per_task  # before any stop
        self.stop = self.planned if stop is None else min(stop, self.planned)

    def __len__(self) -> int:
        return self.stop

    def after(self, done: int) -> Iterator[RoundPlan]:
        """The steps after the first ``done``, one at a time."""
        return (self[i] for i in range(done, len(self)))

    @overload
    def __getitem__(self, index: int) -> RoundPlan: ...
    @overload
    def __getitem__(self, index: slice) -> list[RoundPlan]: ...
    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(index)
        k, i = divmod(index, self.per_task)
        last = self.task_ends and i == self.per_task - 1  # plain FL has no task end
        return RoundPlan(index + 1, k, i == 0, last)


def schedule(config: ExperimentConfig) -> Schedule:
    """The run's steps; with ``federated.dp.target_epsilon``, only the rounds whose
    releases keep the accountant's epsilon within it (one release a round)."""
    tasks = list(config.continual.tasks)
    if not tasks:
        steps = Schedule([ALL], config.federated.rounds, task_ends=False)
    else:
        steps = Schedule(tasks, config.continual.rounds_per_task)
    dp = config.federated.dp
    if dp.enabled and dp.target_epsilon > 0:
        rate = config.federated.fraction
        stop = releases_within(dp.target_epsilon, dp.noise_multiplier, rate, dp.delta, len(steps))
        steps = Schedule(steps.tasks, steps.per_task, steps.task_ends, stop)
    return steps
