"""Shared fixtures (small synthetic datasets written through the real generator, stores,
servers) and nothing else: what the tests share besides fixtures is in tests/support."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.checkout import REPO, ignored, untracked_files
from tests.support.ports import free_port, wait_healthy

# torch, MLflow and fedlgr are imported by the fixtures that use them: pytest-xdist's
# controller process loads this file too, and runs no test (~16 s of imports saved).


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
    changed = ignored(REPO, [p for p in set(after) & set(before) if after[p] != before[p]])
    if new or changed:
        listing = [f"new: {p}" for p in new] + [f"changed: {p}" for p in changed]
        more = f" (and {len(listing) - 20} more)" if len(listing) > 20 else ""
        pytest.fail(
            f"the tests wrote into the checkout {REPO} (they must write only into pytest's "
            f"temp folders): {'; '.join(listing[:20])}{more}",
            pytrace=False,
        )


@pytest.fixture(scope="session", autouse=True)
def session_empty_store(tmp_path_factory) -> Path:
    """One migrated, empty MLflow store per session (each xdist worker its own), which every
    new sqlite store a test makes - in this process or a child - starts as a copy of
    (``$FEDLGR_EMPTY_STORE``): MLflow's migrations take seconds per store."""
    path = tmp_path_factory.mktemp("empty-store") / "mlflow-empty.db"
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("FEDLGR_EMPTY_STORE", str(path))
        yield path


@pytest.fixture(scope="session")
def synth_dir(tmp_path_factory) -> Path:
    """48 synthetic scenes at 32 px (read-only: copy it before changing anything)."""
    out = tmp_path_factory.mktemp("synth") / "manners-synth"
    from fedlgr.shell.data.synth import synthesize

    synthesize(out, scenes=48, seed=7, size=32)
    return out


@pytest.fixture
def one_thread():
    """Tiny tensors: one thread is fastest and immune to other processes on the machine."""
    import torch

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


@pytest.fixture
def telemetry_setting_restored():
    """``fedlgr.shell.cli.main`` sets MLFLOW_DISABLE_TELEMETRY in this process: undo it."""
    from tests.support.processes import TELEMETRY

    before = os.environ.get(TELEMETRY)
    yield
    if before is None:
        os.environ.pop(TELEMETRY, None)
    else:
        os.environ[TELEMETRY] = before


# --------------------------------------------------------------------------- training runs


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> str:
    return f"sqlite:///{tmp_path_factory.mktemp('mlflow')}/mlflow.db"


# --------------------------------------------------------------------------- servers


@pytest.fixture(scope="module")
def mlflow_server(tmp_path_factory):
    """A real ``mlflow server`` on a free localhost port, shared by a test module's tests
    (it takes ~18 s to start); each test logs to its own experiment."""
    tmp_path = tmp_path_factory.mktemp("mlflow-server")
    from fedlgr.shell.tracking.store import open_client

    open_client(f"sqlite:///{tmp_path}/server.db")  # a copy of the empty store: no migrations
    port = free_port()
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mlflow",
            "server",
            "--backend-store-uri",
            f"sqlite:///{tmp_path}/server.db",
            "--artifacts-destination",
            str(tmp_path / "artifacts"),
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        # ~18 s here (LIBRARY-NOTES)
        wait_healthy(url, process, lambda: process.stderr.read()[-2000:], timeout=120)
        yield url
    finally:
        process.terminate()
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
