"""The sweep's MLflow parent run: the store and experiment its trials are tracked in, the
run that holds them as children, and the best trial logged on it once the study is done."""

from __future__ import annotations

import json
from typing import Any

from fedlgr.errors import FedlgrError
from fedlgr.shell.config import load_config
from fedlgr.shell.sweep.space import SweepSpec
from fedlgr.shell.sweep.trials import all_failed, describe_param, one_line, trial_table
from fedlgr.shell.tracking.context import run_tags
from fedlgr.shell.tracking.experiments import share_view
from fedlgr.shell.tracking.mlflow_run import experiment_id, open_client, store_errors, tracking_uri
from fedlgr.shell.tracking.store import store_lock
from fedlgr.shell.tracking.uri import mask_password, resolve_uri

PARENT_ATTR = "mlflow_parent_run_id"


class ParentRun:
    """The parent run of a study's trials: created by the study's first worker, found by the others,
    RUNNING again when a sweep resumes. A relaunched study goes on in its parent run's experiment,
    whatever the sweep now asks (``moved`` says why)."""

    def __init__(self, spec: SweepSpec, study, storage: str, tracking_uri: str | None):
        self.spec, self.study, self.storage = spec, study, storage
        self.tracking_uri = tracking_uri
        self.experiment = spec.experiment
        self.moved: str | None = None  # why the trials go to another experiment than asked
        self.client, self.experiment_id = self._open_store()
        with store_lock(storage):  # two workers starting at once make one parent run
            self.run_id = self._find_or_create()

    def tracking_overrides(self) -> list[str]:
        """The ``tracking.*`` overrides of every trial's config: its store and experiment."""
        out = [f"tracking.experiment={self.experiment}"]
        if self.tracking_uri:
            out.append(f"tracking.uri={self.tracking_uri}")
        return out

    def _open_store(self):
        """The MLflow client of the trials' store and the id of their experiment."""
        base, overrides = self.spec.trial_config_args({})
        try:
            probe = load_config(base, [*overrides, *self.tracking_overrides()])
            uri = tracking_uri(probe)
        except FedlgrError:  # e.g. data.path left to the grid's config choice
            uri = resolve_uri(self.tracking_uri)
        self.tracking_uri = uri
        # a store another process holds (a sweep stopped mid-write) is one line, as for fedlgr run
        with store_errors(uri, "open the sweep's store"):
            client = open_client(uri)  # creates (migrates) a fresh sqlite store, locked
            parent = self._existing(client)
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

    def _existing(self, client):
        """The study's parent run, when the study has one (a relaunch), else None."""
        run_id = self.study.user_attrs.get(PARENT_ATTR)
        if not run_id:
            return None
        # lazy: mlflow (~5 s), not needed to check a sweep file
        from mlflow.exceptions import MlflowException

        try:
            return client.get_run(run_id)
        except MlflowException as err:
            if err.error_code != "RESOURCE_DOES_NOT_EXIST":
                raise
            raise FedlgrError(
                f"study {self.study.study_name!r}: its MLflow parent run {run_id} is not in "
                f"{mask_password(client.tracking_uri)} ({one_line(err)}); relaunch it with the "
                "--tracking-uri it ran with, or start a new study with --study NAME"
            ) from err

    def _find_or_create(self) -> str:
        """The parent run's id: the study's own (set RUNNING again), else a new run with
        the sweep's settings as its params and tags."""
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
        self._log_settings(run_id)
        # The printed link's view shows the trials and their swept settings.
        share_view(self.client, self.experiment_id, [p.name for p in spec.params], run_id)
        if spec.path is not None:
            self.client.log_artifact(run_id, str(spec.path))
        self.study.set_user_attr(PARENT_ATTR, run_id)
        return run_id

    def _log_settings(self, run_id: str) -> None:
        """The sweep's settings as the parent run's params."""
        # lazy: mlflow (~5 s), not needed to check a sweep file
        from mlflow.entities import Param

        spec = self.spec
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

    def end(self, status: str) -> None:
        """End the parent run with ``status`` (KILLED, FAILED)."""
        self.client.set_terminated(self.run_id, status)

    def finish(self) -> dict[str, Any] | None:
        """Log the best trial (tags ``best.*``, metric ``best/<metric>``, ``best_trial.json``) and
        end the parent run FINISHED, or FAILED when every trial failed; under the storage's lock, as
        every worker that sees the study done may get here."""
        with store_lock(self.storage):
            best = self._log_best()
            self.client.log_dict(self.run_id, trial_table(self.study), "trials.json")
            self.end("FAILED" if all_failed(self.study) else "FINISHED")
            return best

    def _log_best(self) -> dict[str, Any] | None:
        """The best trial, logged on the parent run unless it already is; None when no
        trial completed."""
        if not any(t.state.name == "COMPLETE" for t in self.study.get_trials(deepcopy=False)):
            return None
        trial = self.study.best_trial
        best = {
            "trial": trial.number,
            "value": trial.value,
            "metric": self.spec.metric,
            "params": trial.params,
            "mlflow_run_id": trial.user_attrs.get("mlflow_run_id"),
        }
        key = f"best/{self.spec.metric}"
        logged = self.client.get_run(self.run_id).data
        shown = logged.metrics.get(key)
        if logged.tags.get("best.trial") == str(trial.number) and shown == trial.value:
            return best
        tags = {"best.trial": str(trial.number), "best.run_id": str(best["mlflow_run_id"])}
        tags.update({f"best.{k}": str(v) for k, v in trial.params.items()})
        for name, value in tags.items():
            self.client.set_tag(self.run_id, name, value)
        self.client.log_metric(self.run_id, key, trial.value)
        self.client.log_dict(self.run_id, best, "best_trial.json")
        return best
