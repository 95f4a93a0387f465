"""FCL metrics (docs/methods.md): scores after each task, and the forgetting of past tasks.

"After Task k" is measured at the end of task k's last round, on the test scenes of all
tasks seen so far (the paper: after Task 1 on circle, after Task 2 on circle + arrow), and
on each task's scenes. The forgetting of a past task j, at any later point, is per client
its score now minus its score just after task j was learnt, over the clients as their
scores' headline is (``RoundLog.over_clients``: the mean, simulated attackers apart), with a
sign that makes positive mean forgotten: a score where lower is better (loss, RMSE) now -
then, one where higher is better (PCC) then - now. Every score of
:data:`fedlgr.core.metrics.SCORES` is followed.
"""

from __future__ import annotations

import math

import numpy as np

from fedlgr.core.metrics import SCORES
from fedlgr.core.records import RoundLog

METRICS = tuple(s.name for s in SCORES)
_SIGN = {s.name: -1.0 if s.higher_is_better else 1.0 for s in SCORES}


def _sign(metric: str) -> float:
    return _SIGN[metric]


class ForgettingTracker:
    def __init__(self, tasks: list[str]):
        self.tasks = tasks
        self.learnt: dict[str, dict[str, np.ndarray]] = {}  # task -> metric -> per client
        self.after: list[dict[str, float]] = []  # per finished task: its summary figures

    def forgetting(self, log: RoundLog) -> dict[str, float]:
        """Forgetting of every task learnt before the one being trained."""
        out = {}
        for task, then in self.learnt.items():
            if task == log.task:
                continue
            for m in METRICS:
                now = log.column(f"task/{task}/{m}")
                value = log.over_clients(_sign(m) * (now - then[m]))  # the scores' headline
                out[f"forgetting/{task}/{m}"] = math.nan if value is None else value
        return out

    def end_of_task(self, log: RoundLog, k: int) -> dict[str, float]:
        """Record task k as learnt; the "after task k+1" summary figures."""
        self.learnt[log.task] = {m: log.column(f"task/{log.task}/{m}").copy() for m in METRICS}
        prefix = f"after_task{k + 1}"
        out = {f"{prefix}/test/{m}": log.mean(f"test/{m}") for m in METRICS}
        for task in self.tasks[: k + 1]:
            out.update({f"{prefix}/task/{task}/{m}": log.mean(f"task/{task}/{m}") for m in METRICS})
        out.update({f"{prefix}/{k}": v for k, v in self.forgetting(log).items()})
        self.after.append(out)
        return out
