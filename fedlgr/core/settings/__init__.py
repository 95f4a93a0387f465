"""The experiment's settings, declared once (:mod:`.model`, with the vocabulary of
:mod:`.declare` and the rules across settings of :mod:`.rules`): the core's input type.
The shell loads them from YAML and the command line (:mod:`fedlgr.shell.config`)."""

from fedlgr.core.settings.model import (
    DEFAULT_TASKS,
    ContinualConfig,
    DataConfig,
    DeployConfig,
    DPConfig,
    ExperimentConfig,
    FaultsConfig,
    FederatedConfig,
    ModelConfig,
    NoiseConfig,
    RuntimeConfig,
    SecAggConfig,
    TaskSpec,
    TrackingConfig,
    TrainConfig,
    default_cache_dir,
)

__all__ = [
    "DEFAULT_TASKS",
    "ContinualConfig",
    "DPConfig",
    "DataConfig",
    "DeployConfig",
    "ExperimentConfig",
    "FaultsConfig",
    "FederatedConfig",
    "ModelConfig",
    "NoiseConfig",
    "RuntimeConfig",
    "SecAggConfig",
    "TaskSpec",
    "TrackingConfig",
    "TrainConfig",
    "default_cache_dir",
]
