"""One worker of a sweep: runs the study's trials one at a time until it is done (or interrupted),
each a ``fedlgr run`` child of the sweep's MLflow parent run whose rounds go to the pruner."""

from __future__ import annotations

import contextlib
import json
import time
import warnings
from collections.abc import Callable

from fedlgr.errors import FedlgrError, interrupt_in
from fedlgr.shell.config import ExperimentConfig, load_config
from fedlgr.shell.config.export import config_hash
from fedlgr.shell.signals import Terminated, deferred
from fedlgr.shell.sweep.ownership import TrialOwnership
from fedlgr.shell.sweep.parent_run import ParentRun
from fedlgr.shell.sweep.space import SweepSpec
from fedlgr.shell.sweep.storage import DEFAULT_STORAGE, open_study, storage_error
from fedlgr.shell.sweep.trials import counts, duplicate_of, failing, one_line, ran, stopped_early
from fedlgr.shell.tracking.context import trial_config


class PrunedRun(Exception):
    """A trial pruned: raised from a run's ``on_round`` hook when the pruner stops it, the run ends
    KILLED (see :func:`fedlgr.shell.run.experiment.run_experiment`), or for a point already run."""

    mlflow_status = "KILLED"


def interrupt_reason(err: KeyboardInterrupt) -> str:
    """What stopped a trial, as its ``interrupted`` user attribute says it."""
    if isinstance(err, Terminated):  # SIGTERM or SIGHUP, each named as itself
        return f"stopped by {err.args[0] if err.args else 'SIGTERM'}"
    return "stopped by Ctrl-C"


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
        self.number = worker
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
            self.ownership.held = None
            self._report_last(time.perf_counter() - start)
            self.stopped = failing(self.study, spec, self.since)
            if self.stopped:
                return False

    def _objective(self, trial) -> float:
        """Optuna's objective: the trial is claimed as this worker's, then run; its value of the
        objective's metric. An interrupt held by :attr:`unborn` since ask() is raised here, once
        the trial is claimed, so that it is recorded and queued again."""
        # lazy: optuna (~1 s), not needed to check a sweep file
        import optuna

        self.last_trial = trial.number
        self.ownership.claim(trial)
        try:
            self.unborn.close()
            return self._train(trial)
        except PrunedRun as err:
            raise optuna.TrialPruned(str(err)) from None
        except KeyboardInterrupt as err:  # the table shows the trial interrupted, and why
            trial.set_user_attr("interrupted", interrupt_reason(err))
            raise
        except Exception as err:  # recorded where the end-of-sweep table and MLflow show it
            self._record_error(trial, one_line(err)[:1000])
            raise

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

    def _record_error(self, trial, error: str) -> None:
        """The trial's error as its user attribute ``error`` and as the tag ``fedlgr.error`` of its
        MLflow run - or, failed before its run began, the tag ``trial.N.error`` of the parent."""
        trial.set_user_attr("error", error)
        run_id = trial.user_attrs.get("mlflow_run_id")
        key = "fedlgr.error" if run_id else f"trial.{trial.number}.error"
        try:
            self.parent.client.set_tag(run_id or self.parent.run_id, key, error)
        except Exception as problem:  # never raised over the trial's own error
            self.echo(f"=== trial {trial.number}: could not tag MLflow: {one_line(problem)}")

    def _train(self, trial) -> float:
        """Draw the trial's point and run it; its value of the objective's metric."""
        from fedlgr.shell.run.experiment import run_experiment  # lazy: torch, lightning (~10 s)

        spec = self.spec
        params = self._draw(trial)
        # tracked where the sweep's trials go, named after its point
        base, overrides = spec.trial_config_args(params)
        config = load_config(base, [*overrides, *self.parent.tracking_overrides()])
        config = trial_config(config, params)
        tags = {
            "sweep": spec.name,
            "study": self.study.study_name,
            "trial": str(trial.number),
            "fedlgr.kind": "trial",
            "swept": json.dumps(params),  # what the report shows the best trial won with
        }
        result = run_experiment(
            config,
            parent_run_id=self.parent.run_id,  # not nested=True: MLflow's run stack is per thread
            tags=tags,
            echo=self.echo,
            on_round=self._pruning(trial),
            on_start=lambda run_id: trial.set_user_attr("mlflow_run_id", run_id),
            resume=self._resumable(trial, config),
            show_runs=False,  # the sweep shows them at its end
        )
        trial.set_user_attr("mlflow_run_id", result.run_id)
        final = result.final_metrics()
        if spec.metric not in final:
            known = ", ".join(sorted(k for k in final if "client" not in k))
            raise FedlgrError(
                f"objective.metric={spec.metric}: this run did not log it; it logged {known}"
            )
        return final[spec.metric]

    def _draw(self, trial) -> dict:
        """The trial's point; a point an earlier trial covers is skipped (pruned)."""
        params = {p.name: p.suggest(trial) for p in self.spec.params}
        twin = duplicate_of(self.study, trial.number, params)
        if twin is not None:
            trial.set_user_attr("duplicate_of", twin)
            raise PrunedRun(f"the same point as trial {twin}")
        shown = " ".join(f"{k}={v}" for k, v in params.items())
        self.echo(f"\n=== {self.spec.name} trial {trial.number} (worker {self.number}): {shown}")
        return params

    def _pruning(self, trial) -> Callable[[int, dict[str, float]], None]:
        """The run's ``on_round`` hook: each round's value goes to the pruner, which may stop the
        run (:class:`PrunedRun`); an end-only objective (``mean/...``) by its ``test/...`` value."""
        metric = self.spec.metric
        intermediate = (
            metric
            if not metric.startswith(("after_task", "mean/"))
            else "test/" + metric.rsplit("/", 1)[-1]
        )

        def on_round(round_: int, metrics: dict[str, float]) -> None:
            if intermediate in metrics:
                with warnings.catch_warnings():  # a resumed run shows its rounds again
                    warnings.filterwarnings("ignore", message=".*already reported")
                    trial.report(metrics[intermediate], round_)
                if trial.should_prune():
                    trial.set_user_attr("pruned_at_round", round_)
                    raise PrunedRun(f"pruned after round {round_}")

        return on_round

    def _resumable(self, trial, config: ExperimentConfig) -> str | None:
        """A retried trial's MLflow run, when it left a checkpoint: the copy carries the failed
        trial's ``mlflow_run_id`` and reported rounds, so the retry resumes that run."""
        # lazy: torch (~5 s), loaded by the checkpoint modules
        from fedlgr.shell.run.checkpoint import checkpoints
        from fedlgr.shell.run.resume import checkpoint_folder

        run_id = trial.user_attrs.get("mlflow_run_id")
        failed = self.study._storage.get_trial(trial._trial_id).system_attrs.get("failed_trial")
        if failed is None or not run_id:
            return None
        try:
            run = self.parent.client.get_run(run_id)
        except Exception:  # the run is gone from the store: start over
            return None
        if run.info.status == "FINISHED" or not checkpoints(checkpoint_folder(run, config)):
            return None
        if run.data.tags.get("fedlgr.config_hash") != config_hash(config):
            changed = f"settings changed since run {run_id}"
            self.echo(f"=== trial {trial.number}: {changed}; it starts from round 1")
            return None
        self.echo(f"=== trial {trial.number} continues run {run_id} of trial {failed}")
        return run_id
