"""Checks of a config that need this machine or its runtime: a scholar too large for the memory,
faults simulated where the robots are real (the settings' own rules are the core's)."""

from __future__ import annotations

import itertools

from fedlgr.core.data.columns import FEATURE_COLUMNS
from fedlgr.core.settings import ExperimentConfig
from fedlgr.core.settings.rules import format_bytes
from fedlgr.errors import ConfigError

MOBILENET_V2_NUMBERS = 2_258_036  # parameters and buffers of torchvision's features, width 1


def machine_memory() -> int:
    """This machine's memory in bytes (``psutil.virtual_memory().total``)."""
    import psutil  # lazy: psutil is heavy, and the config loads before any run (fedlgr --help)

    return psutil.virtual_memory().total


def check_machine(config: ExperimentConfig) -> None:
    """Refuse a scholar too large to train in this machine's memory, before it is built."""
    m = config.model
    if config.root_kind == "mlp":
        sizes = (len(FEATURE_COLUMNS), *m.mlp_hidden)
        # Linear weights and bias, BatchNorm weight, bias and running mean and variance
        root = sum(a * b + 5 * b for a, b in itertools.pairwise(sizes))
        out, setting = sizes[-1], f"model.mlp_hidden={list(m.mlp_hidden)}"
    else:  # the number of MobileNetV2's weights grows with the square of its width
        root = round(MOBILENET_V2_NUMBERS * m.width**2)
        out, setting = round(1280 * max(1.0, m.width)), f"model.width={m.width}"
    h = m.top_hidden
    numbers = root + 4 * out + out * h + h + 4 * h + 8 * h + 8  # BN, Linear, BN, Linear
    need, have = 16 * numbers, machine_memory()
    if need > have:
        raise ConfigError(
            f"{setting} with model.top_hidden={h}: the scholar holds ~{numbers:.2g} "
            f"parameters and buffers, {format_bytes(need)} to train (4 bytes each for the "
            "weights, gradients and Adam's two moments), more than this machine's "
            f"{format_bytes(have)} of memory (psutil.virtual_memory().total)"
        )


def check_robots_are_real(config: ExperimentConfig) -> None:
    """A run on robots (Flower) simulates no fault: its robots are real. Checked where the
    run is submitted and again by the ServerApp (the config may live on its machine only)."""
    faults = config.federated.faults
    if faults != type(faults)():
        raise ConfigError(
            "federated.faults: faults are simulated in one process or Fabric's processes "
            "(fedlgr run); robots on Flower are real and nothing is simulated there"
        )
