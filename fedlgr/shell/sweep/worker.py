"""One worker of a sweep: runs the study's trials one at a time until it is done (or interrupted),
each as a ``fedlgr run`` child of the sweep's MLflow parent run."""

from __future__ import annotations

import contextlib
import time
import warnings
from collections.abc import Callable

from fedlgr.errors import interrupt_in
from fedlgr.shell.signals import deferred
from fedlgr.shell.sweep.ownership import TrialOwnership
from fedlgr.shell.sweep.parent_run import ParentRun
from fedlgr.shell.sweep.space import SweepSpec
from fedlgr.shell.sweep.storage import DEFAULT_STORAGE, open_study, storage_error
from fedlgr.shell.sweep.trial_run import TrialRunner
from fedlgr.shell.sweep.trials import counts, failing, ran, stopped_early


class Worker:
    """Runs trials of one study until it is done (or interrupted)."""

    def __init__(
        self,
        spec: SweepSpec,
        storage: str = DEFAULT_STORAGE,
        *,
        study_name: str | None = None,
        tracking_uri: str | None = None,
        worker: int = 0,
        echo: Callable[..., None] = print,
        settings_changed: bool = False,
    ):
        self.spec, self.storage, self.echo = spec, storage, echo
        self.study, retry = open_study(spec, storage, study_name, worker, settings_changed)
        self.parent = ParentRun(spec, self.study, storage, tracking_uri)
        retry.client, retry.experiment_id = self.parent.client, self.parent.experiment_id
        self.ownership = TrialOwnership(spec, self.study, retry, worker, echo)
        self.runner = TrialRunner(spec, self.study, self.parent, worker, echo)
        self.last_trial: int | None = None
        # this launch's trials are numbered from here: an earlier launch's failures do not stop it
        self.since = len(self.study.get_trials(deepcopy=False))
        self.stopped: str | None = None  # why it stopped on failing trials
        # an interrupt between ask() and the objective waits, else ask()'s trial stays RUNNING
        self.unborn = contextlib.ExitStack()

    @property
    def experiment(self) -> str:
        """The MLflow experiment this worker's trials go to (the parent run's)."""
        return self.parent.experiment

    @property
    def parent_run_id(self) -> str:
        return self.parent.run_id

    def run(self) -> bool:
        """Run trials until the study is done; True when it is, False when trials kept
        failing (:attr:`stopped` says why)."""
        # lazy: optuna (~1 s), not needed to check a sweep file
        import optuna

        optuna.logging.set_verbosity(optuna.logging.ERROR)  # we print one line per trial
        with self._guarded(self._requeue_interrupted, failed="FAILED"):
            return self._run()

    def left_to_run(self) -> bool:
        """Whether the study has a trial left to start, running or queued - once the
        trials of dead or interrupted workers are queued again."""
        # no trial of ours yet: on an interrupt the parent run ends KILLED
        with self._guarded(lambda: self.parent.end("KILLED")):
            self.ownership.recover()
            return counts(self.study, self.spec) != (0, 0, 0)

    @contextlib.contextmanager
    def _guarded(self, interrupted: Callable[[], None], failed: str | None = None):
        """Optuna's heartbeats without their "experimental" warning; ``interrupted()`` on Ctrl-C or
        SIGTERM (also behind Optuna's own error); a failure of the study's storage (full, locked,
        damaged) as one line, the parent run ended ``failed``."""
        # lazy: optuna (~1 s), not needed to check a sweep file
        import optuna

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            try:
                yield
            except KeyboardInterrupt:  # Ctrl-C, or SIGTERM under fedlgr.shell.signals
                interrupted()
                raise
            except Exception as err:
                interrupt = interrupt_in(err)
                if interrupt is not None:
                    interrupted()
                    raise interrupt from None
                problem = storage_error(self.storage, err)
                if problem is None:
                    raise
                if failed:
                    with contextlib.suppress(Exception):  # MLflow's store is another one
                        self.parent.end(failed)
                raise problem from err

    def _run(self) -> bool:
        spec = self.spec
        while True:
            self.ownership.recover()
            if self.ownership.someone_is_drawing():
                time.sleep(0.5)  # let it take its point first (GridSampler may hand it out twice)
                continue
            todo, running, waiting = counts(self.study, spec)
            if todo == 0 and waiting == 0:
                if running == 0:
                    if why := stopped_early(self.study, spec):
                        done = f"{ran(self.study)} of {spec.n_trials} trials"
                        self.echo(f"sweep {spec.name}: stopped after {done}: {why}")
                    return True
                # Another worker is still busy: wait, in case it dies and its trial returns.
                time.sleep(min(5.0, spec.heartbeat_s / 2))
                continue
            start = time.perf_counter()
            try:
                self.unborn.enter_context(deferred())
                self.study.optimize(self._objective, n_trials=1, catch=(Exception,))
            except ValueError as err:  # Optuna's "Cannot tell a FAIL trial."
                if not str(err).startswith("Cannot tell a"):
                    raise
                # declared dead elsewhere while this process was stopped; queued again there
                self.echo(
                    f"=== trial {self.last_trial}: another worker declared this one dead while "
                    "it was stopped and queued the trial again; its result here is dropped"
                )
            finally:
                self.unborn.close()  # no trial began (the study's storage failed in ask())
            self.ownership.release()
            self._report_last(time.perf_counter() - start)
            self.stopped = failing(self.study, spec, self.since)
            if self.stopped:
                return False

    def _objective(self, trial) -> float:
        """Optuna's objective: the trial is claimed as this worker's, then run."""
        self.last_trial = trial.number
        self.ownership.claim(trial)
        return self.runner.run(trial, self.unborn)

    def _requeue_interrupted(self) -> None:
        """Ctrl-C or SIGTERM: queue this worker's trial again so the next launch redoes it
        and end the parent run KILLED."""
        try:
            self.ownership.requeue_held()
        finally:
            self.parent.end("KILLED")

    def _report_last(self, seconds: float) -> None:
        if self.last_trial is None:
            return
        t = self.study.get_trials(deepcopy=False)[self.last_trial]
        if "duplicate_of" in t.user_attrs or not t.state.is_finished():
            return
        what = {
            "COMPLETE": f"{self.spec.metric} {t.value:.4f}" if t.value is not None else "",
            "PRUNED": f"pruned after round {t.user_attrs.get('pruned_at_round', '?')}",
            "FAIL": f"FAILED: {t.user_attrs.get('error', 'see the log above')}",
        }[t.state.name]
        self.echo(f"=== trial {t.number}: {what} ({seconds:.0f} s)")
        self.last_trial = None
