"""Shared fixtures: small synthetic datasets written through the real generator."""

from __future__ import annotations

import contextlib
import csv
import os
import shutil
import subprocess
from pathlib import Path

import mlflow
import pytest
import torch

from fedlgr.config import CONF_DIR, load_config
from fedlgr.data.columns import ALL_COLUMNS
from fedlgr.data.synth import synthesize

FAST = CONF_DIR / "debug" / "tiny.yaml"  # the cheapest run through the image path
REPO = Path(__file__).resolve().parents[1]
# Written by Python, pytest and the linters wherever they run: not the suite's doing.
CACHES = frozenset({".git", ".venv", "__pycache__", ".pytest_cache", ".ruff_cache", ".mypy_cache"})


def untracked_files(root: Path, skip: Path | None = None) -> dict[str, tuple[int, int]] | None:
    """``{path: (size, mtime_ns)}`` of every file in git checkout ``root`` that git does not
    track (untracked and ignored ones: ``mlruns/``, ``mlflow.db``, its lock ...), caches and
    ``skip`` left out; None when ``root`` is not the top of a git checkout."""
    try:
        top = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--show-toplevel"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        listed = subprocess.run(
            ["git", "-C", str(root), "ls-files", "-z"], capture_output=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    if Path(top).resolve() != root.resolve():
        return None
    tracked = set(os.fsdecode(listed).split("\0"))
    found = {}
    for folder, dirs, files in os.walk(root):
        here = Path(folder)
        dirs[:] = [d for d in dirs if d not in CACHES and (skip is None or here / d != skip)]
        for name in files:
            path = here / name
            relative = path.relative_to(root).as_posix()
            if relative not in tracked:
                with contextlib.suppress(OSError):  # removed meanwhile
                    stat = path.lstat()
                    found[relative] = (stat.st_size, stat.st_mtime_ns)
    return found


def _ignored(root: Path, paths: list[str]) -> list[str]:
    """Those of ``paths`` (relative to git checkout ``root``) that git ignores, sorted."""
    if not paths:
        return []
    found = subprocess.run(
        ["git", "-C", str(root), "check-ignore", "-z", "--stdin"],
        input="\0".join(paths).encode(),
        capture_output=True,
    ).stdout
    return sorted(p for p in os.fsdecode(found).split("\0") if p)


@pytest.fixture(scope="session", autouse=True)
def checkout_unchanged(tmp_path_factory):
    """Tests write only into pytest's temp folders: after the session, the checkout holds no
    file git does not track that it did not hold before, and no ignored file changed (a
    developer's own ``mlruns/``, ``mlflow.db`` or data may be there; they are compared, not
    required to be absent).
    Skipped outside a git checkout (an installed package's tests)."""
    basetemp = tmp_path_factory.getbasetemp().resolve()
    before = untracked_files(REPO, basetemp)
    yield
    if before is None:
        return
    after = untracked_files(REPO, basetemp) or {}
    new = sorted(set(after) - set(before))
    # A changed file counts where git ignores it (a store, an artifact): an untracked source
    # file may be one a person is editing meanwhile.
    changed = _ignored(REPO, [p for p in set(after) & set(before) if after[p] != before[p]])
    if new or changed:
        listing = [f"new: {p}" for p in new] + [f"changed: {p}" for p in changed]
        more = f" (and {len(listing) - 20} more)" if len(listing) > 20 else ""
        pytest.fail(
            f"the tests wrote into the checkout {REPO} (they must write only into pytest's "
            f"temp folders): {'; '.join(listing[:20])}{more}",
            pytrace=False,
        )


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
