"""One MLflow run per experiment run (rank 0 only).

Default store: MLflow 3's sqlite file ``mlflow.db`` in the working directory with
artifacts under ``mlruns/`` (the plain file store is refused by MLflow 3);
``$MLFLOW_TRACKING_URI`` or ``tracking.uri`` (``--tracking-uri``) point elsewhere, e.g. at
an ``mlflow server``. Params are the flattened resolved config; metrics are logged per
round with ``step=round``; artifacts are the resolved config, the per-round/per-client
results CSV and a PNG of RMSE/PCC per round; at the end ``mean/cost/*`` hold the costs
per client per round averaged over clients and rounds (what Tables III/IV report). A run
that fails is ended FAILED (KILLED on Ctrl-C or when a sweep prunes it) after saving what
it had.
"""

from __future__ import annotations

import csv
import io
import os
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from fedlgr.config import ExperimentConfig, flatten, to_yaml

DEFAULT_URI = "sqlite:///mlflow.db"


def resolve_uri(uri: str | None) -> str:
    """``uri`` if given, else ``$MLFLOW_TRACKING_URI``, else the local sqlite store."""
    return uri or os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_URI


def tracking_uri(config: ExperimentConfig) -> str:
    return resolve_uri(config.tracking.uri)


def experiment_id(client, name: str) -> str:
    """The id of MLflow experiment ``name``, created if it does not exist yet."""
    experiment = client.get_experiment_by_name(name)
    return experiment.experiment_id if experiment is not None else client.create_experiment(name)


def dataset_name(config: ExperimentConfig) -> str:
    path = Path(config.data.path)
    return "synthetic" if (path / "synth.json").is_file() else path.name


class Tracker:
    """Starts the run on creation; ``log_round`` per round; ``finish`` or ``fail`` at the end."""

    def __init__(
        self,
        config: ExperimentConfig,
        tags: dict[str, str] | None = None,
        parent_run_id: str | None = None,
    ):
        import mlflow

        self.mlflow = mlflow
        self.client = mlflow.MlflowClient(tracking_uri(config))
        self.experiment_id = experiment_id(self.client, config.tracking.experiment)
        run_tags = {
            "method": config.method_name,
            "strategy": config.federated.strategy,
            "scope": config.federated.scope,
            "dataset": dataset_name(config),
            "modality": config.data.modality,
            "clients": str(config.data.clients),
            "augmentation": str(config.data.augment).lower(),
            "benchmark": "FCL" if config.continual_learning else "FL",
            "continual": config.continual.method if config.continual_learning else "none",
            **(tags or {}),
        }
        if parent_run_id:
            run_tags["mlflow.parentRunId"] = parent_run_id
        run = self.client.create_run(self.experiment_id, run_name=config.run_name, tags=run_tags)
        self.run_id = run.info.run_id
        params = flatten(config)
        from mlflow.entities import Param

        items = [Param(k, v[:6000]) for k, v in params.items()]
        for i in range(0, len(items), 100):  # the REST API takes 100 params per batch
            self.client.log_batch(self.run_id, params=items[i : i + 100])
        self.client.log_text(self.run_id, to_yaml(config), "config.yaml")

    def log_round(self, round_: int, metrics: dict[str, float]) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, round_) for k, v in metrics.items()]
        for i in range(0, len(items), 1000):
            self.client.log_batch(self.run_id, metrics=items[i : i + 1000])

    def log_summary(self, metrics: dict[str, float]) -> None:
        """Run-level values (no round): e.g. ``mean/cost/cpu_s`` over clients and rounds."""
        if metrics:
            self.log_round(0, metrics)

    def save_results(self, rows: Sequence[dict[str, object]], curves_png: bytes | None) -> None:
        if rows:
            buffer = io.StringIO()
            writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
            writer.writeheader()
            writer.writerows(rows)
            self.client.log_text(self.run_id, buffer.getvalue(), "results.csv")
        if curves_png:
            self._log_bytes(curves_png, "curves.png")

    def _log_bytes(self, data: bytes, name: str) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / name
            path.write_bytes(data)
            self.client.log_artifact(self.run_id, str(path))

    def finish(self) -> None:
        self.client.set_terminated(self.run_id, "FINISHED")

    def fail(self, interrupted: bool = False) -> None:
        self.client.set_terminated(self.run_id, "KILLED" if interrupted else "FAILED")
