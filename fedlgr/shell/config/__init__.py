"""Experiment settings (declared in :mod:`fedlgr.core.settings`) loaded from YAML and ``key=value``
and written out; import from here: ``from fedlgr.shell.config import load_config``."""

import importlib
from typing import Any

# Where each public name lives, imported when first asked for (PEP 562): `fedlgr --help` and
# the verbs' declarations import this package without paying for pydantic and OmegaConf.
_HOMES = {
    name: module
    for module, names in {
        "fedlgr.core.methods": "FCL_METHODS METHODS method_name",
        "fedlgr.core.settings": (
            "DEFAULT_TASKS ContinualConfig DataConfig DeployConfig ExperimentConfig "
            "FaultsConfig FederatedConfig ModelConfig RuntimeConfig TaskSpec "
            "TrackingConfig TrainConfig default_cache_dir"
        ),
        "fedlgr.core.settings.rules": (
            "MAX_AUGMENT_COPIES MAX_EXPERIMENT_NAME MAX_IMAGE_SIZE MAX_INTERVAL_S "
            "MAX_PER_MACHINE MAX_ROUNDS MIN_IMAGE_SIZE MOBILENET_V2_BLOCKS"
        ),
        "fedlgr.errors": "ConfigError",
        "fedlgr.shell.config.export": (
            "flatten known_settings robot_yaml short_setting to_plain to_yaml"
        ),
        "fedlgr.shell.config.files": "CONF_DIR SETTING_NAME SWEEPS_DIR find_config yaml_reason",
        "fedlgr.shell.config.written": "check_interpolations",
        "fedlgr.shell.config.load": "check_sent_settings config_from_data load_config",
    }.items()
    for name in names.split()
}


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = globals()[name] = getattr(importlib.import_module(_HOMES[name]), name)
    return value


__all__ = sorted(_HOMES)
