"""Sweeps: Optuna studies over fedlgr configs, tracked in MLflow (``fedlgr sweep``)."""

from fedlgr.shell.sweep.spec import load_sweep
from fedlgr.shell.sweep.study import run_sweep

__all__ = ["load_sweep", "run_sweep"]
