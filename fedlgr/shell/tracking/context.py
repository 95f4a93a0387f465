"""What an MLflow run says about itself beyond its numbers, so that a person can tell runs
apart in the UI: its name, MLflow's context tags, its params, its dataset and the
machine's load while it ran.

* **Name**: ``tracking.run_name``, else the method and setting with the modality
  (``FedAvg-2c-noaug-image``); a sweep trial's name adds its swept values
  (``FedLGR-2c-noaug-image lr_root=1e-05 replay=4``).
* **Context tags**: ``MlflowClient.create_run`` records none; MLflow's own resolver
  (:func:`mlflow.tracking.context.registry.resolve_tags`, what ``mlflow.start_run`` uses)
  adds ``mlflow.user``, ``mlflow.source.name`` / ``type`` and ``mlflow.source.git.commit``
  (of the command's checkout, else of fedlgr's own, see :func:`run_tags`).
* **Params**: the flattened config without machine-local paths (the data folder, the
  image cache, the store, the checkpoint folder: they differ from machine to machine and
  say nothing about the method; ``config.yaml`` keeps them); pretrained weights by file
  name.
* **Dataset**: one ``log_input`` of the scenes table (one row per scene, ratings
  averaged) with the data folder as its source: name, digest, schema and row count, no
  data uploaded (none where the folder is not on this machine, e.g. a Flower server).
* **System metrics**: MLflow's :class:`SystemMetricsMonitor` (CPU, memory, disk,
  network, NVIDIA/AMD GPU when there is one) attached to the run by id, every
  ``tracking.system_metrics_s`` seconds; one last sample when the run ends, so even a
  short run shows some. Machine-wide figures, not per client (per-client costs are the
  ``cost/*`` metrics).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from fedlgr.core.data.columns import CSV_NAME
from fedlgr.errors import first_line
from fedlgr.shell.config import ExperimentConfig, flatten, short_setting
from fedlgr.shell.tracking.store import store_lock

# Paths that belong to this machine, not to the experiment.
LOCAL_PATHS = frozenset({"data.path", "data.cache_dir", "tracking.uri", "tracking.checkpoint_dir"})
# Not params either: the run's name is its name (as a param, it differs between a sweep's
# trials and pushes a swept setting out of MLflow's compare plot, which draws the first 3
# params that differ, sorted by name).
NOT_PARAMS = LOCAL_PATHS | {"tracking.run_name"}
NAMED_WEIGHTS = ("none", "imagenet")


def run_name(config: ExperimentConfig) -> str:
    """The run's one name, in MLflow and on the console: ``tracking.run_name``, else e.g.
    ``FedAvg-2c-noaug-image``."""
    return config.tracking.run_name or f"{config.run_name}-{config.data.modality}"


def trial_config(config: ExperimentConfig, params: Mapping[str, Any]) -> ExperimentConfig:
    """``config`` named after its method and swept values, short enough for MLflow's runs
    table: ``FedLGR lr_root=1e-05 lgr.replay=stored`` (a setting without its section,
    unless two swept settings share that; a swept method by its name alone). The trial
    runs under its sweep's parent run, which holds what all trials share."""
    swept = {k: v for k, v in params.items() if k != "method"}
    last = [short_setting(name) for name in swept]
    shown = " ".join(
        f"{short if last.count(short) == 1 else name}={value}"
        for (name, value), short in zip(swept.items(), last, strict=True)
    )
    name = f"{config.method_name} {shown}".strip()
    return dataclasses.replace(config, tracking=dataclasses.replace(config.tracking, run_name=name))


def run_tags(tags: Mapping[str, str]) -> dict[str, str]:
    """``tags`` with MLflow's context tags (source, user, git commit) added. MLflow takes
    the commit of the checkout that holds the command (``sys.argv[0]``), and none when the
    command is git-ignored, as ``.venv/bin/fedlgr`` is: then the commit (branch, remote) is
    that of the checkout fedlgr's own code runs from, if any."""
    # lazy: mlflow (seconds), only once a run is created
    from mlflow.tracking.context.registry import resolve_tags
    from mlflow.utils import git_utils
    from mlflow.utils.mlflow_tags import MLFLOW_GIT_BRANCH, MLFLOW_GIT_COMMIT, MLFLOW_GIT_REPO_URL

    out = resolve_tags(dict(tags))
    if MLFLOW_GIT_COMMIT not in out:
        code = str(Path(__file__).resolve().parent)
        for key, find in (
            (MLFLOW_GIT_COMMIT, git_utils.get_git_commit),
            (MLFLOW_GIT_BRANCH, git_utils.get_git_branch),
            (MLFLOW_GIT_REPO_URL, git_utils.get_git_repo_url),
        ):
            if (value := find(code)) is not None:
                out[key] = value
    return out


def run_params(config: ExperimentConfig) -> dict[str, str]:
    """The flattened config as params, without machine-local paths and the run's name."""
    params = {k: v for k, v in flatten(config).items() if k not in NOT_PARAMS}
    weights = config.model.weights
    if weights not in NAMED_WEIGHTS:
        params["model.weights"] = Path(weights).name
    return params


def data_digest(config: ExperimentConfig) -> str:
    """A digest of the data a run trains on: the bytes of ``data.path``'s ratings CSV and,
    for images, of every file under its ``images/`` folder (names included). "" where the
    data is not on this machine (a Flower server). Recorded in the run's checkpoints and
    tag ``fedlgr.data_digest``: ``--resume`` on other data is refused. (MLflow's dataset
    digest covers the ratings table only, not the images.)"""
    folder = Path(config.data.path).expanduser().resolve()
    table = folder / CSV_NAME
    if not table.is_file():
        return ""
    digest = hashlib.sha256(table.read_bytes())
    images = folder / "images"
    if config.data.modality == "image" and images.is_dir():
        for path in sorted(images.rglob("*")):
            if path.is_file():
                digest.update(b"\0" + path.relative_to(images).as_posix().encode() + b"\0")
                digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def log_dataset(client, run_id: str, config: ExperimentConfig, name: str) -> None:
    """Record the scenes table of ``data.path`` as the run's dataset input."""
    # lazy: mlflow and pandas (seconds), only once a run is created
    import mlflow.data
    import pandas as pd
    from mlflow.data.dataset_source_registry import get_dataset_source_from_json
    from mlflow.entities import DatasetInput, InputTag

    from fedlgr.shell.data.ratings import read_ratings  # lazy: imports numpy at its top

    folder = Path(config.data.path).expanduser().resolve()
    if not (folder / CSV_NAME).is_file():  # e.g. a Flower server: the data is on the robots
        return
    table = read_ratings(folder)
    frame = pd.DataFrame({"stamp": table.stamps, **table.values, "n_ratings": table.n_ratings})
    source = get_dataset_source_from_json(json.dumps({"uri": str(folder)}), "local")
    with warnings.catch_warnings():
        # MLflow's digest calls pandas in a way pandas 4 will refuse: MLflow's to fix.
        warnings.filterwarnings("ignore", message="Starting with pandas version 4.0")
        dataset = mlflow.data.from_pandas(frame, source=source, name=name)
        # The stamp is an integer column and never missing.
        warnings.filterwarnings("ignore", message="Hint: Inferred schema contains integer")
        entity = dataset._to_mlflow_entity()  # infers the schema
    tags = [
        InputTag("mlflow.data.context", "training"),
        InputTag("modality", config.data.modality),
    ]
    # MLflow's sqlite store looks the dataset up, then inserts it: two runs starting at once
    # on one store both inserted it, and one died on the UNIQUE constraint. One at a time.
    with store_lock(client.tracking_uri):
        client.log_inputs(run_id, datasets=[DatasetInput(entity, tags=tags)])


class FirstLine(logging.Filter):
    """Keeps a record to one line: its message's first, and its exception's first (the
    traceback dropped). For MLflow's loggers, which log a failed store write with the
    SQL statement, its parameters and two stack traces before fedlgr's one-line error."""

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage().strip()
        line = text.splitlines()[0][:300] if text else text
        if record.exc_info and record.exc_info[1] is not None:
            cause = str(record.exc_info[1]).strip()
            line = f"{line.rstrip('.')}: {cause.splitlines()[0][:300] if cause else ''}"
        record.msg, record.args = line, None
        record.exc_info = record.exc_text = None
        return True


def one_line_logs(*names: str) -> None:
    """:class:`FirstLine` on each named logger (once)."""
    for name in names:
        log = logging.getLogger(name)
        if not any(isinstance(f, FirstLine) for f in log.filters):
            log.addFilter(FirstLine())


class SystemMetrics:
    """MLflow's system-metrics monitor on run ``run_id`` (no active run needed): sampled
    every ``interval`` seconds in a background thread; :meth:`stop` joins it and logs a
    last sample. ``resume``: go on from the run's last system-metrics step."""

    def __init__(self, run_id: str, uri: str, interval: float, resume: bool = False):
        # lazy: mlflow (seconds), only once a run starts
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        # It announces its start and stop at INFO on every run: not news. A failed write
        # is logged with the whole SQL statement and its parameters: one line is enough.
        logging.getLogger("mlflow.system_metrics").setLevel(logging.WARNING)
        # (A logger's filter sees only its own records: the monitor module's logger.)
        one_line_logs("mlflow.system_metrics.system_metrics_monitor")
        self.monitor = SystemMetricsMonitor(
            run_id, sampling_interval=interval, resume_logging=resume, tracking_uri=uri
        )
        self.monitor.start()

    def stop(self) -> None:
        """Stop sampling and log what was sampled since the last step (a short run's only
        one), before the run is ended. Never raises: the run's end matters more."""
        monitor, self.monitor = self.monitor, None
        if monitor is None:
            return
        monitor.finish()  # joins the thread and flushes what it had logged
        try:
            monitor.collect_metrics()
            monitor.publish_metrics(monitor.aggregate_metrics())
            monitor.mlflow_logger.flush()
        except Exception as err:  # the store went away: the run's end reports it
            first = first_line(err, 200)
            warnings.warn(f"last system-metrics sample not logged: {first}", stacklevel=2)
