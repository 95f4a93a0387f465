"""The wheel: an installed fedlgr (pip, ``uv tool install``) finds its configs and sweeps."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import yaml

from fedlgr.shell.config import CONF_DIR, SWEEPS_DIR

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    uv = shutil.which("uv")
    if uv is None:
        pytest.skip("uv is not on PATH: cannot build the wheel")
    out = tmp_path_factory.mktemp("dist")
    done = subprocess.run(
        [uv, "build", "--wheel", "--out-dir", str(out), str(REPO)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    (path,) = out.glob("fedlgr-*.whl")
    return path


@pytest.mark.slow  # builds the wheel
def test_the_wheel_ships_every_config_and_sweep(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    configs = {f"fedlgr/conf/{p.relative_to(CONF_DIR)}" for p in CONF_DIR.rglob("*.yaml")}
    sweeps = {f"fedlgr/sweeps/{p.name}" for p in SWEEPS_DIR.glob("*.yaml")}
    assert "fedlgr/conf/experiment/demo.yaml" in configs and "fedlgr/sweeps/ewc.yaml" in sweeps
    assert configs <= names and sweeps <= names
    assert not [n for n in names if n.startswith(("conf/", "sweeps/"))]  # nothing top-level
    metadata = next(n for n in names if n.endswith(".dist-info/METADATA"))
    assert "Requires-Dist: tqdm" in zipfile.ZipFile(wheel).read(metadata).decode()


@pytest.mark.slow
def test_an_unpacked_wheel_runs_outside_the_checkout(wheel, tmp_path):
    """The wheel's files alone (its dependencies from this environment), from a folder
    outside the repository: demo --help, the shipped sweeps, a shipped config by name."""
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}  # ahead of the checkout's editable install

    def fedlgr(*argv: str) -> str:
        done = subprocess.run(
            [sys.executable, "-m", "fedlgr", *argv],
            cwd=elsewhere,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 0, done.stderr
        return done.stdout

    demo = fedlgr("demo", "--help")
    assert "--scenes INTEGER" in demo and "[default: 1000]" in demo
    sweeps = fedlgr("sweep", "--help")
    assert f"\n  shipped sweeps (in {site / 'fedlgr' / 'sweeps'}):\n" in sweeps
    assert "  ewc " in sweeps and "  paper_fl " in sweeps
    printed = fedlgr("run", "conf/debug/fast.yaml", "data.path=/data/x", "--print-config")
    config = yaml.safe_load(printed)
    assert config["data"]["path"] == "/data/x"
    assert _settings(yaml.safe_load((CONF_DIR / "debug" / "fast.yaml").read_text())) <= (
        _settings(config)
    )  # every setting of the shipped file, as it reads
    assert list(elsewhere.iterdir()) == []


def _settings(tree: dict, prefix: str = "") -> set[tuple[str, str]]:
    """``{("train.epochs", "1"), ...}``: a nested mapping's leaves."""
    leaves = set()
    for key, value in tree.items():
        if isinstance(value, dict):
            leaves |= _settings(value, f"{prefix}{key}.")
        else:
            leaves.add((f"{prefix}{key}", repr(value)))
    return leaves


def test_deployment_secrets_and_robot_state_are_git_ignored():
    """What `fedlgr deploy` writes where the README runs it is never committed by mistake:
    the CA's and the robots' private keys, the robots' state, the SuperLink's database."""
    root = Path(__file__).resolve().parents[1]
    if not (root / ".git").exists():
        pytest.skip("not a git checkout")
    paths = [
        "creds/ca.key",
        "creds/robot0",
        "creds/robot0.pub",
        "robots/robot0/run-1/client-0.ckpt",
        "link.db",
        "link.db-wal",
        "link.db-shm",
        "mlflow.db.lock",  # the store's lock, beside it after `fedlgr demo`
        "deploy/server.key",
    ]
    out = subprocess.run(
        ["git", "check-ignore", "--no-index", *paths],
        cwd=root,
        capture_output=True,
        text=True,
        check=False,
    )
    assert out.stdout.split() == paths, out.stderr
