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

if TYPE_CHECKING:
    from fedlgr.shell.config import ExperimentConfig


ALL = "all"  # the single task of plain FL


class Schedule(Sequence[RoundPlan]):
    """The run's steps, made on demand: a run of a billion rounds holds no billion
    ``RoundPlan`` objects (``len`` and indexing are arithmetic). ``tasks[plan.task]`` is
    a step's task name."""

    def __init__(self, tasks: list[str], rounds_per_task: int, task_ends: bool = True):
        self.tasks, self.per_task, self.task_ends = tasks, rounds_per_task, task_ends

    def __len__(self) -> int:
        return len(self.tasks) * self.per_task

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
    tasks = list(config.continual.tasks)
    if not tasks:
        return Schedule([ALL], config.federated.rounds, task_ends=False)
    return Schedule(tasks, config.continual.rounds_per_task)
