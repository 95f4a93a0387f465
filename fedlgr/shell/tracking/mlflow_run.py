"""One MLflow run per experiment run (rank 0 only), :class:`Tracker`: params, metrics at
``step=round``, artifacts, a heartbeat, and a resume that logs nothing twice (docs/tracking.md)."""

from __future__ import annotations

import contextlib
import csv
import functools
import io
import os
import re
import socket
import tempfile
import threading
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

from fedlgr.core.data.columns import LABEL_SHORT_NAMES
from fedlgr.core.metrics import HEADLINE, headline_scores
from fedlgr.errors import interrupt_in
from fedlgr.shell.config import ExperimentConfig, to_yaml
from fedlgr.shell.config.export import config_hash
from fedlgr.shell.signals import deferred
from fedlgr.shell.tracking import context
from fedlgr.shell.tracking.experiments import COST_COLUMNS, experiment_id
from fedlgr.shell.tracking.liveness import process_started
from fedlgr.shell.tracking.store import open_client, store_errors, store_lock
from fedlgr.shell.tracking.uri import resolve_uri


def tracking_uri(config: ExperimentConfig) -> str:
    return resolve_uri(config.tracking.uri)


def dataset_name(config: ExperimentConfig) -> str:
    path = Path(config.data.path)
    return "synthetic" if (path / "synth.json").is_file() else path.name


def _uncut(method):
    """A store write that Ctrl-C / SIGTERM does not cut in half (see fedlgr.shell.signals), its
    failure one line (:func:`~fedlgr.shell.tracking.store.store_errors`)."""
    what = method.__name__.strip("_").replace("_", " ")

    @functools.wraps(method)
    def write(self, *args, **kwargs):
        with deferred(), store_errors(self.uri, f"{what} (run {self.run_id})"):
            return method(self, *args, **kwargs)

    return write


SENTINEL = "round/seconds"  # logged last in each round: the round is wholly logged
# logged right after the scores: MLflow's UI lists a run's metrics in the order first written
HEADLINE_COSTS = ("cost/cpu_s", "cost/gpu_util", "cost/bytes_up")


def note_keys() -> list[str]:
    """The figures a run's description opens with, those of the runs table's shared view:
    the headline scores, then the costs per client per round."""
    return [*(f"test/{s.name}" for s in headline_scores()), *COST_COLUMNS]


_CLIENT = re.compile(r"(^|/)client\d+(/|$)")


def is_detail(key: str) -> bool:
    """A per-client (``test/client0/rmse``) or per-action (``test/rmse/vacuum``) metric:
    logged to MLflow only with ``tracking.detail_metrics`` (results.csv always has them)."""
    return bool(_CLIENT.search(key)) or key.rsplit("/", 1)[-1] in LABEL_SHORT_NAMES


def headline_first(metrics: dict[str, float], detail: bool = False) -> dict[str, float]:
    """``metrics`` as MLflow gets them: the headline scores first, then the forgetting of past
    tasks, the headline costs and the rest; per-client and per-action ones only if ``detail``."""
    kept = {k: v for k, v in metrics.items() if detail or not is_detail(k)}
    first = [k for k in HEADLINE if k in kept]
    first += [k for k in kept if k.startswith("forgetting/")]
    first += [k for k in HEADLINE_COSTS if k in kept]
    return {k: kept[k] for k in dict.fromkeys([*first, *kept])}


class Tracker:
    """Starts the run on creation (or reopens one: :meth:`resume`); ``log_round`` per
    round; ``finish`` or ``fail`` at the end."""

    def __init__(
        self,
        config: ExperimentConfig,
        tags: dict[str, str] | None = None,
        parent_run_id: str | None = None,
        *,
        run_id: str | None = None,
        digest: str = "",
    ):
        self.config = config
        self.system_metrics: context.SystemMetrics | None = None
        self.uri = tracking_uri(config)
        self.run_id: str | None = None
        with store_errors(self.uri, "start the MLflow run"):
            try:
                self._start(config, tags, parent_run_id, run_id, digest)
            except BaseException as err:
                if self.run_id is not None:  # created, then a write failed: not left RUNNING
                    # an interrupt ends it KILLED, as later in the run: stopped, not broken
                    status = "KILLED" if interrupt_in(err) else "FAILED"
                    with contextlib.suppress(Exception):
                        if hasattr(self, "_beat"):
                            self._stop_heartbeat()
                        self.client.set_terminated(self.run_id, status)
                raise

    def _start(self, config, tags, parent_run_id, run_id, digest) -> None:
        self.client = open_client(self.uri)
        with store_lock(self.uri):
            self.experiment_id = experiment_id(self.client, config.tracking.experiment)
        self.done: set[int] = set()  # rounds already wholly logged (a resumed run)
        self.partial: int | None = None  # the round a kill may have cut mid-logging
        if run_id is not None:
            self.run_id = run_id
            self._reopen()
            for key, value in (tags or {}).items():  # e.g. a sweep's new trial number
                self.client.set_tag(self.run_id, key, value)
        else:
            self._create(config, tags, parent_run_id, digest)
        self._start_heartbeat()
        if config.tracking.system_metrics:
            interval = config.tracking.system_metrics_s
            resumed = run_id is not None
            self.system_metrics = context.SystemMetrics(self.run_id, self.uri, interval, resumed)

    def _create(self, config, tags, parent_run_id, digest) -> None:
        """A new run: its tags, params, ``config.yaml`` and dataset input."""
        from mlflow.entities import Param  # lazy: mlflow (seconds), only once a run starts

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
            "fedlgr.config_hash": config_hash(config),
            "runtime": "fabric",  # where the clients ran (fedlgr deploy: flower)
            **({"fedlgr.data_digest": digest} if digest else {}),  # --resume checks it
            **(tags or {}),
        }
        if parent_run_id:
            run_tags["mlflow.parentRunId"] = parent_run_id
        run = self.client.create_run(
            self.experiment_id,
            run_name=context.run_name(config),
            tags=context.run_tags(run_tags),
        )
        self.run_id = run.info.run_id
        flower = run_tags["runtime"] == "flower"
        items = [Param(k, v[:6000]) for k, v in context.run_params(config, flower).items()]
        for i in range(0, len(items), 100):  # the REST API takes 100 params per batch
            self.client.log_batch(self.run_id, params=items[i : i + 100])
        self._log_bytes(to_yaml(config).encode(), "config.yaml")
        context.log_dataset(self.client, self.run_id, config, run_tags["dataset"])

    def _reopen(self) -> None:
        """Resume: RUNNING again; find what is already logged, so it is not logged twice."""
        self.client.update_run(self.run_id, status="RUNNING")
        history = self.client.get_metric_history(self.run_id, SENTINEL)
        self.done = {m.step for m in history}
        self.partial = max(self.done, default=0) + 1

    # ------------------------------------------------------------------ liveness

    def _start_heartbeat(self) -> None:
        self.client.set_tag(self.run_id, "fedlgr.host", socket.gethostname())
        self.client.set_tag(self.run_id, "fedlgr.pid", str(os.getpid()))
        self.client.set_tag(self.run_id, "fedlgr.pid_started", process_started(os.getpid()))
        interval = str(self.config.tracking.heartbeat_s)
        self.client.set_tag(self.run_id, "fedlgr.heartbeat_s", interval)
        self.heartbeat()
        self._stop = threading.Event()
        self._beat = threading.Thread(target=self._beating, name="fedlgr-heartbeat", daemon=True)
        self._beat.start()

    @_uncut
    def heartbeat(self) -> None:
        self.client.set_tag(self.run_id, "fedlgr.heartbeat", f"{time.time():.0f}")

    def _beating(self) -> None:
        warned = False
        while not self._stop.wait(self.config.tracking.heartbeat_s):
            try:
                self.heartbeat()
            except Exception as err:  # the store is away for a moment: the run goes on
                if not warned:
                    message = f"MLflow heartbeat of run {self.run_id} failed: {err}"
                    warnings.warn(message, stacklevel=1)
                    warned = True

    def _stop_heartbeat(self) -> None:
        self._stop.set()
        self._beat.join(timeout=5)
        if self.system_metrics is not None:
            self.system_metrics.stop()

    # ------------------------------------------------------------------ logging

    @_uncut
    def log_round(self, round_: int, metrics: dict[str, float]) -> None:
        """Log a round's metrics at ``step=round``, the sentinel last; a round a resumed run
        had already logged is skipped (its values are the same: the run is deterministic)."""
        if round_ in self.done:
            return
        metrics = headline_first(metrics, self.config.tracking.detail_metrics)
        keys = [k for k in metrics if k != SENTINEL] + ([SENTINEL] if SENTINEL in metrics else [])
        if round_ == self.partial and len(keys) > 1000:  # cut between two batches?
            keys = [k for k in keys if not self._logged_at(k, round_)]
        self._log_metrics({k: metrics[k] for k in keys}, round_)
        self.heartbeat()

    @_uncut
    def log_initial(self, metrics: dict[str, float]) -> None:
        """Figures of the model before round 1 (``federated.server_eval``), at ``step=0``;
        once (a resumed run that had logged them does not again)."""
        if not any(self._logged_at(k, 0) for k in metrics):
            self._log_metrics(metrics, 0)

    def _log_metrics(self, metrics: dict[str, float], step: int) -> None:
        """``metrics`` at ``step``, in order; then system metrics may follow (see
        :class:`~fedlgr.shell.tracking.context.SystemMetrics`)."""
        from mlflow.entities import Metric  # lazy: mlflow (seconds), only once a run starts

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, step) for k, v in metrics.items()]
        for i in range(0, len(items), 1000):  # the REST API takes 1000 metrics per batch
            self.client.log_batch(self.run_id, metrics=items[i : i + 1000])
        if self.system_metrics is not None:
            self.system_metrics.release()

    def _logged_at(self, key: str, step: int) -> bool:
        return any(m.step == step for m in self.client.get_metric_history(self.run_id, key))

    @_uncut
    def log_summary(self, metrics: dict[str, float], rounds: int) -> None:
        """Run-level values of a finished run (e.g. ``mean/cost/cpu_s``) at ``step=rounds``; not
        twice for a resumed run that had logged them before it was stopped."""
        if self.done or self.partial:  # a resumed run: what did its first life log?
            metrics = {k: v for k, v in metrics.items() if not self._logged_at(k, rounds)}
        self._log_metrics(metrics, rounds)

    @_uncut
    def save_results(self, rows: Sequence[dict[str, object]], curves_png: bytes | None) -> None:
        if rows:
            buffer = io.StringIO()
            writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
            writer.writeheader()
            writer.writerows(rows)
            self._log_bytes(buffer.getvalue().encode(), "results.csv")
        if curves_png:
            self._log_bytes(curves_png, "curves.png")

    @_uncut
    def describe(self, heading: str, summary: str, metrics: dict[str, float] | None = None) -> None:
        """The run's description, atop its run page (whose metrics table lists system metrics
        first): the headline figures of ``metrics``, then the summary table the console printed."""
        from mlflow.utils.mlflow_tags import MLFLOW_RUN_NOTE  # lazy: mlflow (seconds)

        shown = [k for k in note_keys() if k in (metrics or {})]
        table = ""
        if shown:
            values = [f"{metrics[k]:.4g}" for k in shown]
            rows = [shown, ["---"] * len(shown), values]
            table = "".join(f"| {' | '.join(row)} |\n" for row in rows) + "\n"
        note = f"**{heading}**\n\n{table}```text\n{summary}\n```\n"
        self.client.set_tag(self.run_id, MLFLOW_RUN_NOTE, note)

    def _log_bytes(self, data: bytes, name: str) -> None:
        # Not ``MlflowClient.log_text``: it leaves a folder in the system temp directory.
        with tempfile.TemporaryDirectory(prefix="fedlgr-") as tmp:
            path = Path(tmp) / name
            path.write_bytes(data)
            self.client.log_artifact(self.run_id, str(path))

    @_uncut
    def finish(self) -> None:
        self._stop_heartbeat()
        self.client.set_terminated(self.run_id, "FINISHED")
        self.finished = True

    @_uncut
    def fail(self, interrupted: bool = False) -> None:
        """End the run FAILED (KILLED if ``interrupted``) - unless it had finished: an
        interrupt that lands just after the end changes nothing."""
        self._stop_heartbeat()
        if not getattr(self, "finished", False):
            self.client.set_terminated(self.run_id, "KILLED" if interrupted else "FAILED")
