"""The MLflow experiment a run goes into: found, or made (perhaps by two processes at once), with
its artifacts beside a local sqlite database and fedlgr's shared view of its runs."""

from __future__ import annotations

from pathlib import Path

from fedlgr.shell.tracking.views import TAG, share_view

# MLflow 3's UI shows an experiment of this kind on its runs table, not on its GenAI traces.
KIND = {"mlflow.experimentKind": "custom_model_development"}


def experiment_id(client, name: str) -> str:
    """The id of MLflow experiment ``name``, created if it does not exist yet (by this
    process or, at the same moment, by another one)."""
    experiment = client.get_experiment_by_name(name)
    if experiment is None:
        try:
            made = _create_experiment(client, name)
        except Exception:
            experiment = client.get_experiment_by_name(name)  # another process created it
            if experiment is None:
                raise
        else:
            _share_view(client, made)  # what the printed link opens
            return made
    for key, value in KIND.items():
        if key not in experiment.tags:  # made by an older fedlgr or by hand
            client.set_experiment_tag(experiment.experiment_id, key, value)
    if TAG not in experiment.tags:
        _share_view(client, experiment.experiment_id)
    return experiment.experiment_id


def _share_view(client, experiment_id: str) -> None:
    """:func:`~fedlgr.shell.tracking.views.share_view`, again if it fails: another process may have
    written the tag in between, and MLflow's SQL store then inserts a duplicate key."""
    try:
        share_view(client, experiment_id)
    except Exception:
        share_view(client, experiment_id)


def artifact_root(uri: str) -> Path | None:
    """Where a local sqlite store's experiments keep their artifacts: ``mlruns/`` beside its
    database, not MLflow's ``./mlruns`` of whatever folder a run starts in; else None."""
    if not uri.startswith("sqlite:///"):
        return None
    database = uri.removeprefix("sqlite:///").split("?", 1)[0]
    if not database or database == ":memory:":
        return None
    return Path(database).expanduser().resolve().parent / "mlruns"


def _create_experiment(client, name: str) -> str:
    """A new experiment; in a local sqlite store with its artifacts under :func:`artifact_root`."""
    root = artifact_root(client.tracking_uri)
    if root is None:
        return client.create_experiment(name, tags=KIND)
    # lazy: mlflow (seconds), only when an experiment is made
    from mlflow.entities import ExperimentTag
    from mlflow.tracking._tracking_service.utils import _get_store

    # root as the store's default artifact root: the location derives from the id made here
    store = _get_store(client.tracking_uri, str(root))
    return store.create_experiment(name, tags=[ExperimentTag(k, v) for k, v in KIND.items()])
