"""Experiment settings filled from YAML and ``key=value``. The settings themselves (type,
default, bounds, doc) are declared once in :mod:`fedlgr.core.settings`, the core's input
type; this package loads them:

- :mod:`.load`: the layers (defaults, a config file and what it ``includes``, found by
  :mod:`.files`, the command line) merged by OmegaConf into the dataclasses, ``${...}``
  kept to the policy of :mod:`.interpolation`, OmegaConf's errors made one line by
  :mod:`.messages`.
- :mod:`.export`: a config written out (YAML, flat MLflow params) and the settings' names.

The names below are the package's public face: ``from fedlgr.shell.config import
load_config, ExperimentConfig``.
"""

from fedlgr.core.methods import FCL_METHODS, METHODS, method_name
from fedlgr.core.settings import (
    DEFAULT_TASKS,
    ContinualConfig,
    DataConfig,
    DeployConfig,
    ExperimentConfig,
    FaultsConfig,
    FederatedConfig,
    ModelConfig,
    RuntimeConfig,
    TaskSpec,
    TrackingConfig,
    TrainConfig,
    default_cache_dir,
)
from fedlgr.core.settings.rules import (
    MAX_AUGMENT_COPIES,
    MAX_EXPERIMENT_NAME,
    MAX_IMAGE_SIZE,
    MAX_INTERVAL_S,
    MAX_PER_MACHINE,
    MAX_ROUNDS,
    MIN_IMAGE_SIZE,
    MOBILENET_V2_BLOCKS,
)
from fedlgr.errors import ConfigError
from fedlgr.shell.config.export import (
    flatten,
    known_settings,
    robot_yaml,
    short_setting,
    to_plain,
    to_yaml,
)
from fedlgr.shell.config.files import CONF_DIR, SETTING_NAME, SWEEPS_DIR, find_config, yaml_reason
from fedlgr.shell.config.interpolation import check_interpolations
from fedlgr.shell.config.load import check_sent_settings, config_from_data, load_config

__all__ = [
    "CONF_DIR",
    "DEFAULT_TASKS",
    "FCL_METHODS",
    "MAX_AUGMENT_COPIES",
    "MAX_EXPERIMENT_NAME",
    "MAX_IMAGE_SIZE",
    "MAX_INTERVAL_S",
    "MAX_PER_MACHINE",
    "MAX_ROUNDS",
    "METHODS",
    "MIN_IMAGE_SIZE",
    "MOBILENET_V2_BLOCKS",
    "SETTING_NAME",
    "SWEEPS_DIR",
    "ConfigError",
    "ContinualConfig",
    "DataConfig",
    "DeployConfig",
    "ExperimentConfig",
    "FaultsConfig",
    "FederatedConfig",
    "ModelConfig",
    "RuntimeConfig",
    "TaskSpec",
    "TrackingConfig",
    "TrainConfig",
    "check_interpolations",
    "check_sent_settings",
    "config_from_data",
    "default_cache_dir",
    "find_config",
    "flatten",
    "known_settings",
    "load_config",
    "method_name",
    "robot_yaml",
    "short_setting",
    "to_plain",
    "to_yaml",
    "yaml_reason",
]
