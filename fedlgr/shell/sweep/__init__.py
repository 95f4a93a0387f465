"""Sweeps: Optuna studies over fedlgr configs, tracked in MLflow (``fedlgr sweep``)."""

from fedlgr.shell.sweep.space import SweepSpec
from fedlgr.shell.sweep.spec import find_sweep, load_sweep
from fedlgr.shell.sweep.storage import DEFAULT_STORAGE
from fedlgr.shell.sweep.study import run_sweep

__all__ = ["DEFAULT_STORAGE", "SweepSpec", "find_sweep", "load_sweep", "run_sweep"]
