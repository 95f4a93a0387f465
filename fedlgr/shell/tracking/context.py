"""What an MLflow run says about itself beyond its numbers, so that a person can tell runs apart in
the UI: its name, context tags, the params it uses, its dataset and the machine's load."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import threading
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from fedlgr.core.data.columns import CSV_NAME
from fedlgr.core.methods import CONTINUAL, STRATEGIES
from fedlgr.errors import first_line
from fedlgr.shell.config import ExperimentConfig, flatten, short_setting
from fedlgr.shell.tracking.store import store_lock

# Paths that belong to this machine, not to the experiment.
LOCAL_PATHS = frozenset({"data.path", "data.cache_dir", "tracking.uri", "tracking.checkpoint_dir"})
# nor the run's name: it differs between trials, pushing swept settings out of the compare plot
NOT_PARAMS = LOCAL_PATHS | {"tracking.run_name"}
NAMED_WEIGHTS = ("none", "imagenet")
# Every method's settings section: a run uses its own strategy's and CL method's only.
SECTIONS = {
    "federated": {m.section for m in STRATEGIES.values() if m.settings is not None},
    "continual": {m.section for m in CONTINUAL.values() if m.settings is not None},
}


def run_name(config: ExperimentConfig) -> str:
    """The run's one name, in MLflow and on the console: ``tracking.run_name``, else e.g.
    ``FedAvg-2c-noaug-image``."""
    return config.tracking.run_name or f"{config.run_name}-{config.data.modality}"


def trial_config(config: ExperimentConfig, params: Mapping[str, Any]) -> ExperimentConfig:
    """``config`` named after its method and swept values, short enough for MLflow's runs table:
    ``FedLGR lr_root=1e-05`` (a setting without its section, unless two swept settings share it)."""
    swept = {k: v for k, v in params.items() if k != "method"}
    last = [short_setting(name) for name in swept]
    shown = " ".join(
        f"{short if last.count(short) == 1 else name}={value}"
        for (name, value), short in zip(swept.items(), last, strict=True)
    )
    name = f"{config.method_name} {shown}".strip()
    return dataclasses.replace(config, tracking=dataclasses.replace(config.tracking, run_name=name))


def run_tags(tags: Mapping[str, str]) -> dict[str, str]:
    """``tags`` with MLflow's context tags (source, user, git commit) added. MLflow finds no commit
    for a git-ignored command (``.venv/bin/fedlgr``): then it is that of fedlgr's own checkout."""
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


def run_params(config: ExperimentConfig, flower: bool = False) -> dict[str, str]:
    """The settings the run uses (:func:`used_settings`) as params, without machine-local
    paths and the run's name; ``flower``: the clients run on Flower (``deploy.*``)."""
    params = {k: v for k, v in flatten(config).items() if k not in NOT_PARAMS}
    weights = config.model.weights
    if weights not in NAMED_WEIGHTS:
        params["model.weights"] = Path(weights).name
    return used_settings(params, flower)


def used_settings(params: Mapping[str, str], flower: bool = False) -> dict[str, str]:
    """``params`` (a flattened config, as strings) without the settings the run does not use: other
    strategies' and CL methods' sections, ``federated.dp.*`` without DP, ``deploy.*`` unless
    ``flower``. Reads only ``params``, so reports apply it to runs that logged every setting too."""
    strategy = STRATEGIES.get(params.get("federated.strategy", ""))
    method = CONTINUAL.get(params.get("continual.method", ""))
    fcl = params.get("continual.tasks", "[]") not in ("[]", "()", "")
    dropped = [f"federated.{s}." for s in SECTIONS["federated"] - {strategy and strategy.section}]
    if fcl:
        dropped += [f"continual.{s}." for s in SECTIONS["continual"] - {method and method.section}]
    else:
        dropped.append("continual.")
    try:
        private = float(params.get("federated.dp.clip", "0")) > 0
    except ValueError:  # not a number: kept, as it was logged
        private = True
    if not private:
        dropped.append("federated.dp.")
    if not flower:
        dropped.append("deploy.")
    return {k: v for k, v in params.items() if not k.startswith(tuple(dropped))}


def data_digest(config: ExperimentConfig) -> str:
    """A digest of the data a run trains on (its ratings CSV and, for images, every file under
    ``images/``): ``--resume`` on other data is refused; "" where the data is not here."""
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
    # MLflow looks the dataset up, then inserts it: two runs at once would die on UNIQUE
    with store_lock(client.tracking_uri):
        client.log_inputs(run_id, datasets=[DatasetInput(entity, tags=tags)])


class FirstLine(logging.Filter):
    """Keeps a record to one line: its message's first, and its exception's first (no traceback);
    for MLflow's loggers, which log a failed store write with its SQL and stack traces."""

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage().strip()
        line = text.splitlines()[0][:300] if text else text
        if record.exc_info and record.exc_info[1] is not None:
            cause = str(record.exc_info[1]).strip()
            line = f"{line.rstrip('.')}: {cause.splitlines()[0][:300] if cause else ''}"
        record.msg, record.args = line, None
        record.exc_info = record.exc_text = None
        return True


class SystemMetrics:
    """MLflow's system-metrics monitor on run ``run_id`` (no active run needed), its samples held
    until :meth:`release`: MLflow's UI lists a run's metrics in the order their keys were first
    written, and the scores must come first. ``resume``: go on from the last step."""

    def __init__(self, run_id: str, uri: str, interval: float, resume: bool = False):
        # lazy: mlflow (seconds), only once a run starts
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        # its start and stop at INFO on every run are not news; a failed write: one line
        logging.getLogger("mlflow.system_metrics").setLevel(logging.WARNING)
        # (A logger's filter sees only its own records: the monitor module's logger.)
        log = logging.getLogger("mlflow.system_metrics.system_metrics_monitor")
        if not any(isinstance(f, FirstLine) for f in log.filters):
            log.addFilter(FirstLine())
        self.monitor = SystemMetricsMonitor(
            run_id, sampling_interval=interval, resume_logging=resume, tracking_uri=uri
        )
        self.released = threading.Event()
        if resume:  # the order of its keys was fixed by its first life
            self.released.set()
        logger = self.monitor.mlflow_logger  # records samples, writes when _should_flush
        due = logger._should_flush
        logger._should_flush = lambda: self.released.is_set() and due()
        self.monitor.start()

    def release(self) -> None:
        """The run's scores are written: its samples may be too (at the next sample)."""
        self.released.set()

    def stop(self) -> None:
        """Stop sampling and log what was sampled since the last step, before the run is ended.
        Never raises: the run's end matters more."""
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
