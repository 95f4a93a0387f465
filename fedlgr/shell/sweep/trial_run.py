"""One trial of a sweep, run: its point drawn, trained as a ``fedlgr run`` child of the sweep's
parent run, its rounds reported to the pruner, its value or why it failed recorded."""

from __future__ import annotations

import contextlib
import json
import warnings
from collections.abc import Callable

from fedlgr.errors import FedlgrError
from fedlgr.shell.config import ExperimentConfig, load_config
from fedlgr.shell.config.export import config_hash
from fedlgr.shell.signals import Terminated
from fedlgr.shell.sweep.parent_run import ParentRun
from fedlgr.shell.sweep.space import SweepSpec
from fedlgr.shell.sweep.trials import duplicate_of, one_line
from fedlgr.shell.tracking.context import trial_config


class PrunedRun(Exception):
    """Raised from a run's ``on_round`` hook when the pruner stops a trial; the run ends
    KILLED (see :func:`fedlgr.shell.run.experiment.run_experiment`)."""

    mlflow_status = "KILLED"


def interrupt_reason(err: KeyboardInterrupt) -> str:
    """What stopped a trial, as its ``interrupted`` user attribute says it."""
    if isinstance(err, Terminated):  # SIGTERM or SIGHUP, each named as itself
        return f"stopped by {err.args[0] if err.args else 'SIGTERM'}"
    return "stopped by Ctrl-C"


class TrialRunner:
    """Runs the trials Optuna hands one worker, each as a child run of the sweep's
    :class:`ParentRun`."""

    def __init__(
        self,
        spec: SweepSpec,
        study,
        parent: ParentRun,
        worker: int,
        echo: Callable[..., None],
    ):
        self.spec, self.study, self.parent = spec, study, parent
        self.worker, self.echo = worker, echo

    def run(self, trial, deferred: contextlib.ExitStack) -> float:
        """The trial's value of the objective's metric. An interrupt held by ``deferred`` since
        ask() is raised here, once the trial is claimed, so that it is recorded and queued again."""
        # lazy: optuna (~1 s), not needed to check a sweep file
        import optuna

        try:
            deferred.close()
            return self._train(trial)
        except optuna.TrialPruned:
            raise
        except KeyboardInterrupt as err:  # the table shows the trial interrupted, and why
            trial.set_user_attr("interrupted", interrupt_reason(err))
            raise
        except Exception as err:  # recorded where the end-of-sweep table and MLflow show it
            self._record_error(trial, one_line(err)[:1000])
            raise

    def _record_error(self, trial, error: str) -> None:
        """The trial's error as its user attribute ``error`` and as a tag in MLflow."""
        trial.set_user_attr("error", error)
        try:
            self.parent.tag_error(trial.number, trial.user_attrs.get("mlflow_run_id"), error)
        except Exception as problem:  # never raised over the trial's own error
            self.echo(f"=== trial {trial.number}: could not tag MLflow: {one_line(problem)}")

    def _train(self, trial) -> float:
        """Draw the trial's point and run it; its value of the objective's metric."""
        import optuna  # lazy: optuna (~1 s), not needed to check a sweep file

        from fedlgr.shell.run.experiment import run_experiment  # lazy: torch, lightning (~10 s)

        spec = self.spec
        params = self._draw(trial)
        try:
            config = self._config(params)
            tags = {
                "sweep": spec.name,
                "study": self.study.study_name,
                "trial": str(trial.number),
                "fedlgr.kind": "trial",
                "swept": json.dumps(params),  # what the report shows the best trial won with
            }
            result = run_experiment(
                config,
                parent_run_id=self.parent.run_id,
                tags=tags,
                echo=self.echo,
                on_round=self._pruning(trial),
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

    def _draw(self, trial) -> dict:
        """The trial's point; a point an earlier trial covers is skipped (pruned)."""
        # lazy: optuna (~1 s), not needed to check a sweep file
        import optuna

        params = {p.name: p.suggest(trial) for p in self.spec.params}
        twin = duplicate_of(self.study, trial.number, params)
        if twin is not None:
            trial.set_user_attr("duplicate_of", twin)
            raise optuna.TrialPruned(f"the same point as trial {twin}")
        shown = " ".join(f"{k}={v}" for k, v in params.items())
        self.echo(f"\n=== {self.spec.name} trial {trial.number} (worker {self.worker}): {shown}")
        return params

    def _config(self, params: dict) -> ExperimentConfig:
        """The trial's config, tracked where the sweep's trials go, named after its point."""
        base, overrides = self.spec.trial_config_args(params)
        config = load_config(base, [*overrides, *self.parent.tracking_overrides()])
        return trial_config(config, params)

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
