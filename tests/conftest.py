"""Shared fixtures: small synthetic datasets written through the real generator."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import mlflow
import pytest
import torch

from fedlgr.config import CONF_DIR, load_config
from fedlgr.data.columns import ALL_COLUMNS
from fedlgr.data.synth import synthesize

FAST = CONF_DIR / "debug" / "tiny.yaml"  # the cheapest run through the image path


@pytest.fixture(scope="session")
def synth_dir(tmp_path_factory) -> Path:
    """48 synthetic scenes at 32 px (read-only: copy it before changing anything)."""
    out = tmp_path_factory.mktemp("synth") / "manners-synth"
    synthesize(out, scenes=48, seed=7, size=32)
    return out


@pytest.fixture
def one_thread():
    """Tiny tensors: one thread is fastest and immune to other processes on the machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def synth_copy(synth_dir, tmp_path) -> Path:
    """A private, writable copy of ``synth_dir``."""
    return Path(shutil.copytree(synth_dir, tmp_path / "data"))


@pytest.fixture
def cache_dir(tmp_path, monkeypatch) -> Path:
    """An empty image cache, also used by code that reads FEDLGR_CACHE_DIR."""
    path = tmp_path / "cache"
    monkeypatch.setenv("FEDLGR_CACHE_DIR", str(path))
    return path


def read_rows(csv_path: Path) -> list[list[str]]:
    with csv_path.open(newline="") as f:
        return list(csv.reader(f))


def write_rows(csv_path: Path, rows: list[list[str]]) -> Path:
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    with csv_path.open("w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)
    return csv_path


def rating_row(stamp: int, circle: bool, labels: list[float], descriptor: float = 0.5) -> list[str]:
    """One CSV row: the given stamp, mode and 8 labels, every descriptor = ``descriptor``."""
    flags = ["1", "0"] if circle else ["0", "1"]
    return [str(stamp), *flags, *[str(descriptor)] * 27, *(f"{v:g}" for v in labels)]


HEADER = list(ALL_COLUMNS)


# --------------------------------------------------------------------------- training runs


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> str:
    return f"sqlite:///{tmp_path_factory.mktemp('mlflow')}/mlflow.db"


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


def read_run(store: str, run_id: str):
    client = mlflow.MlflowClient(store)
    run = client.get_run(run_id)
    artifacts = {a.path for a in client.list_artifacts(run_id)}
    return client, run, artifacts


def results_csv(client, run_id) -> list[dict[str, str]]:
    path = client.download_artifacts(run_id, "results.csv")
    with open(path, newline="") as f:
        return list(csv.DictReader(f))
