"""Which process runs which trial (:data:`OWNER`), and what becomes of a trial whose process is
gone: set FAILED and queued again, unless its worker is alive on this machine, merely stopped."""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from datetime import datetime, timedelta

from fedlgr.shell.sweep.space import SweepSpec
from fedlgr.shell.sweep.storage import RetryStaleTrial, fail_and_retry, retry_failed
from fedlgr.shell.sweep.trials import retried
from fedlgr.shell.tracking.liveness import process_alive, process_started

#: A trial's system attribute naming the process that runs it: [host, pid, start time].
OWNER = "fedlgr_owner"


def alive_here(owner) -> bool:
    """Whether ``owner`` (:data:`OWNER`) is a live process on this machine: the same process, not a
    later one given its pid (the start time tells them apart), and not a zombie."""
    if not isinstance(owner, list) or len(owner) != 3 or owner[0] != socket.gethostname():
        return False
    return str(owner[1]).isdigit() and process_alive(int(owner[1]), str(owner[2]))


class TrialOwnership:
    """The trials of one worker's study: the one it holds, and those of other workers that
    died or were interrupted, which it queues again."""

    def __init__(
        self,
        spec: SweepSpec,
        study,
        retry: RetryStaleTrial,
        worker: int,
        echo: Callable[..., None],
    ):
        self.spec, self.study, self.retry, self.worker, self.echo = spec, study, retry, worker, echo
        self.held: int | None = None  # the storage id of the trial this worker runs
        self.waited_for: set[int] = set()  # trials of live workers here, said once

    def claim(self, trial) -> None:
        """Make ``trial`` this worker's: its worker number, its owner, and a new try."""
        self.held = trial._trial_id
        trial.set_user_attr("worker", self.worker)
        me = [socket.gethostname(), os.getpid(), process_started(os.getpid())]
        self.study._storage.set_trial_system_attr(trial._trial_id, OWNER, me)
        if trial.user_attrs.get("interrupted"):  # a re-queued copy: this run is a new try
            trial.set_user_attr("interrupted", False)

    def requeue_held(self) -> None:
        """Queue this worker's trial again after an interrupt, so the next launch redoes it; Optuna
        has set it FAILED, or left it RUNNING if the interrupt hit its own bookkeeping."""
        if self.held is not None and not fail_and_retry(self.study, self.retry, self.held):
            retry_failed(self.study, self.retry, self.held)

    def recover(self) -> None:
        """Queue again the trials of workers that died or were interrupted."""
        # lazy: optuna (~1 s), not needed to check a sweep file
        import optuna

        self._keep_live_owners()
        optuna.storages.fail_stale_trials(self.study)  # dead workers' trials: re-queued
        self._fail_unborn_trials()
        self._retry_interrupted_trials()

    def someone_is_drawing(self) -> bool:
        """Another worker has started a trial but not yet drawn its parameters."""
        return any(not t.params for t in self._running())

    def _running(self) -> list:
        # lazy: optuna (~1 s), not needed to check a sweep file
        from optuna.trial import TrialState

        return self.study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))

    def _keep_live_owners(self) -> None:
        """Record the heartbeat of trials whose worker is alive here but perhaps stopped (Ctrl-Z, a
        suspended VM), which Optuna would otherwise fail and hand to a second worker."""
        storage = self.study._storage
        for t in self._running():
            if alive_here(t.system_attrs.get(OWNER)):
                storage.record_heartbeat(t._trial_id)
                if t.number not in self.waited_for and t._trial_id != self.held:
                    self.waited_for.add(t.number)
                    pid = t.system_attrs[OWNER][1]
                    self.echo(
                        f"sweep {self.spec.name}: trial {t.number} belongs to process {pid} "
                        "on this machine, which is alive: it is left to that process (if it "
                        f"is stopped, `kill -CONT {pid}` lets it go on)"
                    )

    def _fail_unborn_trials(self) -> None:
        """Fail and queue again a trial whose worker was killed before drawing its parameters
        (RUNNING, no params, no heartbeat: Optuna never fails it); the copy keeps GridSampler's
        ``grid_id``, its point."""
        limit = datetime.now() - timedelta(seconds=2 * self.spec.heartbeat_s + 10)
        for t in self._running():
            if not t.params and t.datetime_start is not None and t.datetime_start < limit:
                fail_and_retry(self.study, self.retry, t._trial_id)

    def _retry_interrupted_trials(self) -> None:
        """Queue any interrupted trial whose worker could not queue it (a second Ctrl-C
        during the first one's clean-up): its point would otherwise count as done."""
        trials = self.study.get_trials(deepcopy=False)
        again = retried(trials)
        for t in trials:
            interrupted = t.state.name == "FAIL" and t.user_attrs.get("interrupted")
            if interrupted and t.number not in again:
                retry_failed(self.study, self.retry, t._trial_id)
