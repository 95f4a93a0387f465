"""Sweeps: Optuna studies over fedlgr configs, tracked in MLflow (``fedlgr sweep``)."""

from fedlgr.shell.sweep.spec import SweepSpec, find_sweep, load_sweep
from fedlgr.shell.sweep.study import DEFAULT_STORAGE, run_sweep

__all__ = ["DEFAULT_STORAGE", "SweepSpec", "find_sweep", "load_sweep", "run_sweep"]
