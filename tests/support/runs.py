"""Training runs: the fast-dev-run config on the test data, an in-process orchestrator of
a config, a run read back from MLflow, and a Ctrl-C raised inside a run."""

from __future__ import annotations

import csv

import mlflow

from fedlgr.core.in_process import Orchestrator
from fedlgr.shell.config import CONF_DIR, load_config
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.splits import make_split
from fedlgr.shell.run.experiment import make_fabric

FAST = CONF_DIR / "debug" / "tiny.yaml"  # the cheapest run through the image path


def fast_config(synth_dir, cache_dir, store, *overrides):
    return load_config(
        FAST,
        [
            f"data.path={synth_dir}",
            f"data.cache_dir={cache_dir}",
            f"tracking.uri={store}",
            *overrides,
        ],
    )


def orchestrator(config) -> Orchestrator:
    """The in-process rounds of ``config``, on its scenes and its split (one process)."""
    scenes = load_scenes(config.data)
    return Orchestrator(make_fabric(config), config, scenes, make_split(scenes.table, config.data))


def read_run(store: str, run_id: str):
    client = mlflow.MlflowClient(store)
    run = client.get_run(run_id)
    artifacts = {a.path for a in client.list_artifacts(run_id)}
    return client, run, artifacts


def results_csv(client, run_id) -> list[dict[str, str]]:
    path = client.download_artifacts(run_id, "results.csv")
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def csv_rounds(rows: list[dict[str, str]]) -> dict[int, list[str]]:
    """The clients of each round in results.csv's rows, by round."""
    out: dict[int, list[str]] = {}
    for row in rows:
        out.setdefault(int(row["round"]), []).append(row["client"])
    return out


class Interrupt(KeyboardInterrupt):
    """Ctrl-C after a given round (the run ends KILLED, its checkpoints stay)."""
