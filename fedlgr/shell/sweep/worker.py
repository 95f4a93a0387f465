"""One worker of a sweep: runs the study's trials one at a time until it is done (or
interrupted), each as a ``fedlgr run`` child of the sweep's MLflow parent run
(:mod:`fedlgr.shell.sweep.study` says how a sweep runs and recovers)."""

from __future__ import annotations

import contextlib
import json
import os
import time
import warnings
from collections.abc import Callable
from typing import Any

from fedlgr.errors import FedlgrError, interrupt_in
from fedlgr.shell.signals import deferred
from fedlgr.shell.sweep.spec import SweepSpec
from fedlgr.shell.sweep.storage import fail_and_retry, open_study, retry_failed, storage_error
from fedlgr.shell.sweep.trials import (
    all_failed,
    counts,
    describe_param,
    duplicate_of,
    no_new_point,
    ran,
    trial_table,
)
from fedlgr.shell.tracking.server import mask_password

DEFAULT_STORAGE = "sqlite:///optuna.db"
PARENT_ATTR = "mlflow_parent_run_id"


class PrunedRun(Exception):
    """Raised from a run's ``on_round`` hook when the pruner stops a trial; the run ends
    KILLED (see :func:`fedlgr.shell.run.experiment.run_experiment`)."""

    mlflow_status = "KILLED"


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}".rstrip(": ")


def _interrupt_reason(err: KeyboardInterrupt) -> str:
    from fedlgr.shell.signals import Terminated

    if isinstance(err, Terminated):  # SIGTERM or SIGHUP (was always "SIGTERM": d03-d158)
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
        from fedlgr.shell.tracking.mlflow_run import store_lock

        self.spec, self.storage, self.worker, self.echo = spec, storage, worker, echo
        self.study, self.retry = open_study(spec, storage, study_name, worker, settings_changed)
        self.tracking_uri = tracking_uri
        self.experiment = spec.experiment  # a study goes on in its parent run's: _mlflow
        self.moved: str | None = None  # why the trials go to another experiment than asked
        self.client, self.experiment_id = self._mlflow()
        self.retry.client, self.retry.experiment_id = self.client, self.experiment_id
        with store_lock(storage):  # two workers starting at once make one parent run
            self.parent_run_id = self._parent()
        self.last_trial: int | None = None
        self.trial_id: int | None = None  # the storage id of the trial this worker runs
        # Ctrl-C / SIGTERM from Optuna's ask() to objective() waits until trial_id is set:
        # the trial it had made was left RUNNING, never queued again (the ninth fault
        # sweep, i17d, i17g: SIGTERM or SIGHUP just as a trial began)
        self.unborn = contextlib.ExitStack()
        self.waited_for: set[int] = set()  # trials of live workers here, said once

    # ------------------------------------------------------------------ MLflow parent run

    def _tracking(self) -> list[str]:
        out = [f"tracking.experiment={self.experiment}"]
        if self.tracking_uri:
            out.append(f"tracking.uri={self.tracking_uri}")
        return out

    def _mlflow(self):

        from fedlgr.shell.config import load_config
        from fedlgr.shell.tracking.mlflow_run import (
            experiment_id,
            open_client,
            resolve_uri,
            store_errors,
            tracking_uri,
        )

        base, overrides = self.spec.trial_config_args({})
        try:
            probe = load_config(base, [*overrides, *self._tracking()])
            uri = tracking_uri(probe)
        except FedlgrError:  # e.g. data.path left to the grid's config choice
            uri = resolve_uri(self.tracking_uri)
        self.tracking_uri = uri
        # One line for a store another process holds (e.g. a stopped sweep in the middle
        # of a write: the seventh fault sweep, g04), as for fedlgr run.
        with store_errors(uri, "open the sweep's store"):
            client = open_client(uri)  # creates (migrates) a fresh sqlite store, locked
            parent = self._parent_run(client)
        if parent is None:
            return client, experiment_id(client, self.experiment)
        # A relaunched study keeps its runs together: its trials go where its parent run is.
        there = client.get_experiment(parent.info.experiment_id).name
        if there != self.experiment:
            self.moved = (
                f"study {self.study.study_name!r}: its parent run is in MLflow experiment "
                f"{there!r}, so its trials go there too (not {self.experiment!r}); "
                "--study NAME starts a new study elsewhere"
            )
        self.experiment = there
        return client, parent.info.experiment_id

    def _parent_run(self, client):
        """The study's parent run, when the study has one (a relaunch), else None."""
        run_id = self.study.user_attrs.get(PARENT_ATTR)
        if not run_id:
            return None
        from mlflow.exceptions import MlflowException

        from fedlgr.shell.tracking.server import check_reachable

        check_reachable(client.tracking_uri)  # one line within seconds, not minutes of retries
        try:
            return client.get_run(run_id)
        except MlflowException as err:
            if err.error_code != "RESOURCE_DOES_NOT_EXIST":
                raise
            raise FedlgrError(
                f"study {self.study.study_name!r}: its MLflow parent run {run_id} is not in "
                f"{mask_password(client.tracking_uri)} ({_one_line(err)}); relaunch it with the "
                "--tracking-uri it ran with, or start a new study with --study NAME"
            ) from err

    def _parent(self) -> str:
        """The sweep's parent run: created by the first worker, found by the others (its id
        is a study user attribute), set RUNNING again when a sweep resumes."""
        from mlflow.entities import Param

        from fedlgr.shell.tracking.context import run_tags
        from fedlgr.shell.tracking.views import share_view

        run_id = self.study.user_attrs.get(PARENT_ATTR)
        if run_id:
            if self.client.get_run(run_id).info.status != "RUNNING":
                self.client.update_run(run_id, status="RUNNING")
            return run_id
        spec = self.spec
        run = self.client.create_run(
            self.experiment_id,
            run_name=f"sweep {self.study.study_name}",
            tags=run_tags(  # MLflow's context tags too: source, user, git commit
                {
                    "fedlgr.kind": "sweep",
                    "sweep": spec.name,
                    "study": self.study.study_name,
                    "sampler": spec.sampler,
                    "objective": f"{spec.direction} {spec.metric}",
                    # a machine-local path for sqlite: not a param; a server's password masked
                    "storage": mask_password(self.storage),
                }
            ),
        )
        run_id = run.info.run_id
        params = {
            "sweep": spec.name,
            "study": self.study.study_name,
            "sampler": spec.sampler,
            "pruner": spec.pruner,
            "objective.metric": spec.metric,
            "objective.direction": spec.direction,
            "trials": spec.n_trials,
            "base": spec.base or "",
            "overrides": " ".join(spec.overrides),
            "space": json.dumps({p.name: describe_param(p) for p in spec.params}),
        }
        self.client.log_batch(run_id, params=[Param(k, str(v)[:6000]) for k, v in params.items()])
        # The printed link's view shows the trials and their swept settings.
        share_view(self.client, self.experiment_id, [p.name for p in spec.params], run_id)
        if spec.path is not None:
            self.client.log_artifact(run_id, str(spec.path))
        self.study.set_user_attr(PARENT_ATTR, run_id)
        return run_id

    def finish_parent(self) -> dict[str, Any] | None:
        """Log the best trial (tags ``best.*``, metric ``best/<metric>``, ``best_trial.json``)
        and end the parent run FINISHED - FAILED when every trial failed. Every worker
        that sees the study done may get here, and a finished sweep launched again does:
        the best trial is logged once (under the storage's lock), not once per process."""
        from fedlgr.shell.tracking.mlflow_run import store_lock

        with store_lock(self.storage):
            return self._finish_parent()

    def _finish_parent(self) -> dict[str, Any] | None:
        from optuna.trial import TrialState

        best = None
        if any(t.state == TrialState.COMPLETE for t in self.study.get_trials(deepcopy=False)):
            trial = self.study.best_trial
            best = {
                "trial": trial.number,
                "value": trial.value,
                "metric": self.spec.metric,
                "params": trial.params,
                "mlflow_run_id": trial.user_attrs.get("mlflow_run_id"),
            }
            key = f"best/{self.spec.metric}"
            logged = self.client.get_run(self.parent_run_id).data
            shown = logged.metrics.get(key)
            already = logged.tags.get("best.trial") == str(trial.number) and shown == trial.value
            if not already:
                tags = {"best.trial": str(trial.number), "best.run_id": str(best["mlflow_run_id"])}
                tags.update({f"best.{k}": str(v) for k, v in trial.params.items()})
                for name, value in tags.items():
                    self.client.set_tag(self.parent_run_id, name, value)
                self.client.log_metric(self.parent_run_id, key, trial.value)
                self.client.log_dict(self.parent_run_id, best, "best_trial.json")
        self.client.log_dict(self.parent_run_id, trial_table(self.study), "trials.json")
        status = "FAILED" if all_failed(self.study) else "FINISHED"
        self.client.set_terminated(self.parent_run_id, status)
        return best

    # ------------------------------------------------------------------ trials

    def objective(self, trial) -> float:
        import optuna

        self.last_trial, self.trial_id = trial.number, trial._trial_id
        trial.set_user_attr("worker", self.worker)
        self.study._storage.set_trial_system_attr(trial._trial_id, OWNER, this_process())
        if trial.user_attrs.get("interrupted"):  # a re-queued copy: this run is a new try
            trial.set_user_attr("interrupted", False)
        try:
            self.unborn.close()  # an interrupt that came since ask() is raised now
            return self._train(trial)
        except optuna.TrialPruned:
            raise
        except KeyboardInterrupt as err:  # the table shows the trial interrupted, and why
            trial.set_user_attr("interrupted", _interrupt_reason(err))
            raise
        except Exception as err:  # recorded where the end-of-sweep table and MLflow show it
            self._record_error(trial, _one_line(err)[:1000])
            raise

    def _record_error(self, trial, error: str) -> None:
        """The trial's error as its user attribute ``error`` and as the tag
        ``fedlgr.error`` of its MLflow run - or, for a trial that failed before its run
        began, as the tag ``trial.N.error`` of the sweep's parent run."""
        trial.set_user_attr("error", error)
        run_id = trial.user_attrs.get("mlflow_run_id")
        try:
            if run_id:
                self.client.set_tag(run_id, "fedlgr.error", error)
            else:
                self.client.set_tag(self.parent_run_id, f"trial.{trial.number}.error", error)
        except Exception as problem:  # never raised over the trial's own error
            self.echo(f"=== trial {trial.number}: could not tag MLflow: {_one_line(problem)}")

    def _train(self, trial) -> float:
        """Draw the trial's point and run it; its value of the objective's metric."""
        import optuna

        from fedlgr.shell.config import load_config
        from fedlgr.shell.run.experiment import run_experiment
        from fedlgr.shell.tracking.context import trial_config

        spec = self.spec
        params = {p.name: p.suggest(trial) for p in spec.params}
        twin = duplicate_of(self.study, trial.number, params)
        if twin is not None:
            trial.set_user_attr("duplicate_of", twin)
            raise optuna.TrialPruned(f"the same point as trial {twin}")
        shown = " ".join(f"{k}={v}" for k, v in params.items())
        self.echo(f"\n=== {spec.name} trial {trial.number} (worker {self.worker}): {shown}")
        intermediate = (
            spec.metric
            if not spec.metric.startswith(("after_task", "mean/"))
            else "test/" + spec.metric.rsplit("/", 1)[-1]
        )

        def on_round(round_: int, metrics: dict[str, float]) -> None:
            if intermediate in metrics:
                with warnings.catch_warnings():  # a resumed run shows its rounds again
                    warnings.filterwarnings("ignore", message=".*already reported")
                    trial.report(metrics[intermediate], round_)
                if trial.should_prune():
                    trial.set_user_attr("pruned_at_round", round_)
                    raise PrunedRun(f"pruned after round {round_}")

        try:
            base, overrides = spec.trial_config_args(params)
            config = load_config(base, [*overrides, *self._tracking()])
            config = trial_config(config, params)  # named after its swept values
            tags = {
                "sweep": spec.name,
                "study": self.study.study_name,
                "trial": str(trial.number),
                "fedlgr.kind": "trial",
                "swept": json.dumps(params),  # what the report shows the best trial won with
            }
            result = run_experiment(
                config,
                parent_run_id=self.parent_run_id,
                tags=tags,
                echo=self.echo,
                on_round=on_round,
                on_start=lambda run_id: trial.set_user_attr("mlflow_run_id", run_id),
                resume=self._resumable(trial, config),
                show_runs=False,  # the sweep shows them at its end
            )
        except PrunedRun as err:
            raise optuna.TrialPruned(str(err)) from None
        trial.set_user_attr("mlflow_run_id", result.run_id)
        final = result.final_metrics()
        if spec.metric not in final:
            known = ", ".join(sorted(k for k in final if "client" not in k))
            raise FedlgrError(
                f"objective.metric={spec.metric}: this run did not log it; it logged {known}"
            )
        return final[spec.metric]

    def _resumable(self, trial, config) -> str | None:
        """A retried trial's MLflow run, when it left a checkpoint to continue from: the
        copy carries the failed trial's user attributes (``mlflow_run_id``, set when its
        run started) and reported rounds, so the retry resumes that run instead of
        training from round 1."""
        from fedlgr.shell.run.checkpoint import checkpoints, fingerprint
        from fedlgr.shell.run.resume import checkpoint_folder

        run_id = trial.user_attrs.get("mlflow_run_id")
        failed = self.study._storage.get_trial(trial._trial_id).system_attrs.get("failed_trial")
        if failed is None or not run_id:
            return None
        try:
            run = self.client.get_run(run_id)
        except Exception:  # the run is gone from the store: start over
            return None
        if run.info.status == "FINISHED" or not checkpoints(checkpoint_folder(run, config)):
            return None
        if run.data.tags.get("fedlgr.config_hash") != fingerprint(config):
            changed = f"settings changed since run {run_id}"
            self.echo(f"=== trial {trial.number}: {changed}; it starts from round 1")
            return None
        self.echo(f"=== trial {trial.number} continues run {run_id} of trial {failed}")
        return run_id

    def run(self) -> bool:
        """Run trials until the study is done; True when it is."""
        import optuna

        optuna.logging.set_verbosity(optuna.logging.ERROR)  # we print one line per trial
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            try:
                return self._run()
            except KeyboardInterrupt:  # Ctrl-C, or SIGTERM under fedlgr.shell.signals
                self._requeue_interrupted()
                raise
            except Exception as err:  # the study's storage failed (full, locked, damaged)
                interrupt = interrupt_in(err)
                if interrupt is not None:
                    self._requeue_interrupted()
                    raise interrupt from None
                problem = storage_error(self.storage, err)
                if problem is None:
                    raise
                with contextlib.suppress(Exception):  # MLflow's store is another one
                    self.client.set_terminated(self.parent_run_id, "FAILED")
                raise problem from err

    def left_to_run(self) -> bool:
        """Whether the study has a trial left to start, running or queued - once the
        trials of dead or interrupted workers are queued again."""
        import optuna

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                self._recover()
            return counts(self.study, self.spec) != (0, 0, 0)
        except KeyboardInterrupt:  # no trial of ours yet: the parent run ends KILLED
            self.client.set_terminated(self.parent_run_id, "KILLED")
            raise
        except Exception as err:  # the study's storage failed (full, locked, damaged)
            interrupt = interrupt_in(err)
            if interrupt is not None:
                self.client.set_terminated(self.parent_run_id, "KILLED")
                raise interrupt from None
            problem = storage_error(self.storage, err)
            if problem is None:
                raise
            raise problem from err

    def _recover(self) -> None:
        """Queue again the trials of workers that died or were interrupted."""
        import optuna

        self._keep_live_owners()
        optuna.storages.fail_stale_trials(self.study)  # dead workers' trials: re-queued
        self._fail_unborn_trials()
        self._retry_interrupted_trials()

    def _keep_live_owners(self) -> None:
        """A trial whose worker is alive on this machine is never declared dead by its
        heartbeat: its worker may be stopped (Ctrl-Z, ``kill -STOP``, a suspended VM)
        with its heartbeat stale, and would then go on with a trial Optuna has failed and
        re-queued (the seventh fault sweep, g04: two workers on one run, and
        ``ValueError: Cannot tell a FAIL trial``). Its heartbeat is recorded here for it;
        a dead worker's, or one on another machine, is left to Optuna's heartbeat."""
        from optuna.trial import TrialState

        storage = self.study._storage
        for t in self.study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            if alive_here(t.system_attrs.get(OWNER)):
                storage.record_heartbeat(t._trial_id)
                if t.number not in self.waited_for and t._trial_id != self.trial_id:
                    self.waited_for.add(t.number)
                    pid = t.system_attrs[OWNER][1]
                    self.echo(
                        f"sweep {self.spec.name}: trial {t.number} belongs to process {pid} "
                        "on this machine, which is alive: it is left to that process (if it "
                        f"is stopped, `kill -CONT {pid}` lets it go on)"
                    )

    def _run(self) -> bool:
        spec = self.spec
        while True:
            self._recover()
            if self._someone_is_drawing():
                time.sleep(0.5)  # let it take its point first (GridSampler may hand it out twice)
                continue
            todo, running, waiting = counts(self.study, spec)
            if todo == 0 and waiting == 0:
                if running == 0:
                    self._say_why_stopped()
                    return True
                # Another worker is still busy: wait, in case it dies and its trial returns.
                time.sleep(min(5.0, spec.heartbeat_s / 2))
                continue
            start = time.perf_counter()
            try:
                self.unborn.enter_context(deferred())
                self.study.optimize(self.objective, n_trials=1, catch=(Exception,))
            except ValueError as err:  # Optuna's "Cannot tell a FAIL trial."
                if not str(err).startswith("Cannot tell a"):
                    raise
                # Declared dead by a worker on another machine while this process was
                # stopped (a suspended VM): that worker has queued it again.
                self.echo(
                    f"=== trial {self.last_trial}: another worker declared this one dead while "
                    "it was stopped and queued the trial again; its result here is dropped"
                )
            finally:
                self.unborn.close()  # no trial began (the study's storage failed in ask())
            self.trial_id = None
            self._report_last(time.perf_counter() - start)

    def _say_why_stopped(self) -> None:
        """A TPE study that ends before ``trials`` because no new point is left says so."""
        spec = self.spec
        done = ran(self.study)
        why = no_new_point(self.study, spec) if spec.sampler != "grid" else None
        if why and done < spec.n_trials:
            self.echo(f"sweep {spec.name}: stopped after {done} of {spec.n_trials} trials: {why}")

    def _someone_is_drawing(self) -> bool:
        """Another worker has started a trial but not yet drawn its parameters."""
        from optuna.trial import TrialState

        running = self.study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
        return any(not t.params for t in running)

    def _fail_unborn_trials(self) -> None:
        """A worker killed between creating a trial and drawing its parameters leaves a
        RUNNING trial with no params and no heartbeat, which Optuna never fails: fail it
        once it is older than the heartbeat grace period (a live trial draws its
        parameters within milliseconds) and queue it again. GridSampler has already given
        it a point (system attr ``grid_id``) and counts a failed trial's point as visited,
        so without the retry - whose copy keeps ``grid_id`` - that point would come back
        only by chance."""
        from datetime import datetime, timedelta

        from optuna.trial import TrialState

        limit = datetime.now() - timedelta(seconds=2 * self.spec.heartbeat_s + 10)
        for t in self.study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            if not t.params and t.datetime_start is not None and t.datetime_start < limit:
                fail_and_retry(self.study, self.retry, t._trial_id)

    def _requeue_interrupted(self) -> None:
        """Ctrl-C or SIGTERM: queue this worker's trial again so the next launch redoes it
        (as for a worker that died) and end the parent run KILLED. Optuna has recorded the
        trial FAILED - or left it RUNNING, if the interrupt hit its own bookkeeping - and a
        finished trial takes no new attributes, so what says it was re-queued is the copy's
        ``retry_history``."""
        try:
            if self.trial_id is not None and not fail_and_retry(
                self.study, self.retry, self.trial_id
            ):
                retry_failed(self.study, self.retry, self.trial_id)
        finally:
            self.client.set_terminated(self.parent_run_id, "KILLED")

    def _retry_interrupted_trials(self) -> None:
        """Queue any interrupted trial whose worker could not queue it (a second Ctrl-C
        during the first one's clean-up): its point would otherwise count as done."""
        from optuna.trial import TrialState

        trials = self.study.get_trials(deepcopy=False)
        retried = {n for t in trials for n in t.system_attrs.get("retry_history", [])}
        for t in trials:
            interrupted = t.state == TrialState.FAIL and t.user_attrs.get("interrupted")
            if interrupted and t.number not in retried:
                retry_failed(self.study, self.retry, t._trial_id)

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


#: A trial's system attribute naming the process that runs it: [host, pid, start time].
OWNER = "fedlgr_owner"


def this_process() -> list:
    import socket

    from fedlgr.shell.tracking.mlflow_run import process_started

    return [socket.gethostname(), os.getpid(), process_started(os.getpid())]


def alive_here(owner) -> bool:
    """Whether ``owner`` (:data:`OWNER`) is a live process on this machine - the same
    process, not a later one given its pid (the start time tells them apart); a zombie
    is not alive (as for a run's process: :func:`~fedlgr.shell.tracking.mlflow_run.dead_reason`)."""
    import socket

    from fedlgr.shell.tracking.mlflow_run import process_alive

    if not isinstance(owner, list) or len(owner) != 3 or owner[0] != socket.gethostname():
        return False
    return str(owner[1]).isdigit() and process_alive(int(owner[1]), str(owner[2]))
