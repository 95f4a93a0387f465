"""Sweeps on the fast-dev-run config: a sweep file, the ``fedlgr sweep`` command line, a
study's trials and the MLflow runs it made."""

from __future__ import annotations

import contextlib
import sqlite3
import sys
from pathlib import Path

import mlflow
import optuna

from .runs import FAST


def write_sweep(tmp_path: Path, synth_dir: Path, cache_dir: Path, name: str = "grid4") -> Path:
    """A 4-point grid on the fast-dev-run config: 2 methods x 2 top learning rates."""
    path = tmp_path / f"{name}.yaml"
    path.write_text(
        f"base: {FAST}\n"
        f"overrides: [data.path={synth_dir}, data.cache_dir={cache_dir}, runtime.threads=1]\n"
        "objective: {metric: test/rmse, direction: minimize}\n"
        "space:\n"
        "  method: [FedAvg, FedRootAvg]\n"
        "  train.lr_top: [0.001, 0.01]\n"
    )
    return path


def trials_by_state(storage: str, name: str) -> dict[str, list[optuna.trial.FrozenTrial]]:
    study = optuna.load_study(study_name=name, storage=storage)
    out: dict[str, list] = {}
    for t in study.get_trials():
        out.setdefault(t.state.name, []).append(t)
    return out


def read_only_rows(db: Path, sql: str) -> list[tuple]:
    """Rows of ``sql`` on a sqlite file opened read-only, [] while it has no tables: a test
    watching a running sweep must not create the tables the sweep is creating (opening the
    file with Optuna would, racing the sweep's own first use)."""
    if not db.is_file():
        return []
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as con:
            return con.execute(sql).fetchall()
    except sqlite3.OperationalError:  # no tables yet
        return []


def child_runs(store: str, experiment: str):
    client = mlflow.MlflowClient(store)
    exp = client.get_experiment_by_name(experiment)
    runs = client.search_runs([exp.experiment_id])
    parents = [r for r in runs if r.data.tags.get("fedlgr.kind") == "sweep"]
    children = [r for r in runs if r.data.tags.get("fedlgr.kind") == "trial"]
    return client, parents, children


def point(params: dict) -> tuple:
    return tuple(sorted(params.items()))


def sweep_command(path: Path, storage: str, store: str, *extra: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "fedlgr",
        "sweep",
        str(path),
        "--storage",
        storage,
        "--tracking-uri",
        store,
        "--heartbeat",
        "1",
        *extra,
    ]
