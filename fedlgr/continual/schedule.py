"""The training schedule: which task each round trains, and where tasks begin and end.

Plain FL is one task, "all", of ``federated.rounds`` rounds; FCL trains the tasks of
``continual.tasks`` in order, ``continual.rounds_per_task`` rounds each. The round loop
walks these steps: task boundaries are read from the schedule, never worked out from
round numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

from fedlgr.config import ExperimentConfig

ALL = "all"  # the single task of plain FL


@dataclass(frozen=True)
class Step:
    round: int  # 1-based, over the whole run
    task: int  # position of the task in the schedule
    task_name: str
    first_of_task: bool
    last_of_task: bool


def schedule(config: ExperimentConfig) -> list[Step]:
    tasks = list(config.continual.tasks)
    if not tasks:
        rounds = config.federated.rounds
        return [Step(r, 0, ALL, r == 1, False) for r in range(1, rounds + 1)]
    per_task = config.continual.rounds_per_task
    steps = []
    for k, name in enumerate(tasks):
        for i in range(per_task):
            steps.append(Step(len(steps) + 1, k, name, i == 0, i == per_task - 1))
    return steps
