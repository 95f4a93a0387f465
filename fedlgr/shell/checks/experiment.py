"""Experiment checks: the rules across the sections of a config - the rounds of a whole
task schedule, a CL method against the scope, server evaluation against the scope,
``method`` against the settings, the tasks against ``data.tasks``, the root against the
modality, the processes against the clients, ``continual.lgr.train_blocks`` against the
root, and the scholar against this machine's memory. :class:`ExperimentConfig` calls
:func:`check_experiment` from ``__post_init__``, after each section has checked its own
(:mod:`.settings`)."""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING

from fedlgr.core.data.columns import FEATURE_COLUMNS
from fedlgr.core.methods import CONTINUAL, STRATEGIES, method_name
from fedlgr.errors import ConfigError
from fedlgr.shell.checks.settings import MAX_ROUNDS, ROUNDS_BOUND
from fedlgr.shell.checks.values import check_numbers, check_seed, format_bytes, machine_memory

if TYPE_CHECKING:
    from fedlgr.shell.config.settings import ExperimentConfig

MOBILENET_V2_NUMBERS = 2_258_036  # parameters and buffers of torchvision's features, width 1
MOBILENET_V2_BLOCKS = 19  # its features' blocks (Root.blocks(); a test checks the model)


def check_experiment(config: ExperimentConfig) -> None:
    """The rules across sections, after each section has checked its own."""
    check_numbers("", config)
    check_seed("seed", config.seed)
    _rounds_in_all(config)
    _method_fits(config)
    _tasks_known(config)
    _root_reads_features(config)
    _processes_have_clients(config)
    _root_reads_images(config)
    _train_blocks(config)
    _model_fits(config)
    _privacy_fits(config)
    _secure_aggregation_fits(config)


def _rounds_in_all(config: ExperimentConfig) -> None:
    """A task schedule's rounds, all tasks together, within MAX_ROUNDS."""
    if config.continual.tasks and config.total_rounds > MAX_ROUNDS:
        raise ConfigError(
            f"continual.rounds_per_task={config.continual.rounds_per_task} x "
            f"{len(config.continual.tasks)} tasks = {config.total_rounds} rounds: "
            f"{ROUNDS_BOUND}"
        )


def _method_fits(config: ExperimentConfig) -> None:
    """The CL method works with the scope, the server holds a model to evaluate, and
    ``method`` names what the settings say."""
    cl = CONTINUAL[config.continual.method]
    if config.federated.scope not in cl.scopes:
        raise ConfigError(
            f"continual.method={cl.key} ({method_name('avg', cl.scopes[0], cl.key)}) works "
            f"with federated.scope={' or '.join(cl.scopes)} only: set "
            f"federated.scope={cl.scopes[0]}"
        )
    if config.federated.server_eval == "on" and config.federated.scope == "root":
        raise ConfigError(
            f"federated.server_eval=on: {config.method_name} shares the root only and "
            "keeps each top on its client, so the server holds no whole model to "
            "evaluate; server evaluation is for full-scope methods (FedAvg, FedBN, "
            "FedProx, FedOpt, FedDistill and their CL variants; 'auto' turns it on "
            "for those only)"
        )
    if config.method is not None and config.method != config.method_name:
        raise ConfigError(f"method={config.method} disagrees with federated/continual settings")


def _tasks_known(config: ExperimentConfig) -> None:
    known = [t.name for t in config.data.tasks]
    unknown = [t for t in config.continual.tasks if t not in known]
    if unknown:
        raise ConfigError(f"continual.tasks: unknown task(s) {unknown}; data.tasks has {known}")


def _root_reads_features(config: ExperimentConfig) -> None:
    if config.data.modality == "features" and config.root_kind != "mlp":
        raise ConfigError(
            f"model.root={config.model.root} reads images, but data.modality=features: "
            "use model.root=mlp (or auto)"
        )


def _processes_have_clients(config: ExperimentConfig) -> None:
    clients = config.data.clients
    if config.runtime.world_size > clients:
        raise ConfigError(
            f"runtime.devices x runtime.num_nodes = {config.runtime.world_size} processes for "
            f"data.clients={clients}: every process needs at least one client"
        )
    if config.federated.faults.byzantine >= clients:
        raise ConfigError(
            f"federated.faults.byzantine={config.federated.faults.byzantine}: fewer than "
            f"data.clients={clients} (an honest client at least)"
        )
    if (config.deploy.min_clients or 0) > clients:
        raise ConfigError(
            f"deploy.min_clients={config.deploy.min_clients} exceeds data.clients={clients}"
        )
    federated = config.federated
    if federated.evaluate == "sample" and federated.eval_clients > clients:
        raise ConfigError(
            f"federated.eval_clients={federated.eval_clients} exceeds data.clients={clients} "
            "(federated.evaluate=sample scores that many clients each round)"
        )


def _root_reads_images(config: ExperimentConfig) -> None:
    if config.data.modality == "image" and config.root_kind == "mlp":
        raise ConfigError("model.root=mlp reads the descriptors: set data.modality=features")


def _train_blocks(config: ExperimentConfig) -> None:
    """``continual.lgr.train_blocks=k`` trains the root's last k blocks: more blocks than
    the root has would train it whole without a word."""
    k = config.continual.lgr.train_blocks
    if k is None or config.continual.method != "lgr" or not config.continual.tasks:
        return
    # Root.blocks() (fedlgr.core.models.scholar): MobileNetV2's features, an MLP's layers
    mlp = config.root_kind == "mlp"
    mlp_hidden = config.model.mlp_hidden
    blocks = len(mlp_hidden) if mlp else MOBILENET_V2_BLOCKS
    if k > blocks:
        what = f"model.mlp_hidden={list(mlp_hidden)}" if mlp else "MobileNetV2"
        raise ConfigError(
            f"continual.lgr.train_blocks={k}: the root ({what}) has {blocks} block"
            f"{'' if blocks == 1 else 's'}; at most {blocks} (null: the whole root trains)"
        )


def _model_fits(config: ExperimentConfig) -> None:
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


def _secure_aggregation_fits(config: ExperimentConfig) -> None:
    """SecAgg+ (``deploy.secagg``) gives the server the sum of the chosen robots' updates
    only: a statistic of the uploads cannot be taken; a round needs two robots or more
    (one robot's "sum" is its update); the sum of the sample counts is rounded to a whole
    number, which the quantisation error must leave unambiguous; under DP each robot's
    weight 1 (and its +-1/2 bit) must fit in ``clipping_range``."""
    secagg, federated = config.deploy.secagg, config.federated
    if not secagg.enabled:
        return
    if _aggregates_a_statistic(federated):
        raise ConfigError(
            f"deploy.secagg.enabled with federated.strategy={federated.strategy}: a "
            f"{federated.strategy} aggregate needs every robot's upload, and SecAgg+ gives "
            f"the server their sum only; {mean_based()}"
        )
    clients, fraction = config.data.clients, federated.fraction
    if federated.dp.enabled and fraction < 1:
        raise ConfigError(
            f"deploy.secagg.enabled with federated.dp and federated.fraction={fraction:g}: "
            "DP samples each robot independently, so a round may choose one robot, whose "
            "update SecAgg+ cannot hide; use federated.fraction=1"
        )
    if (chosen := max(1, round(fraction * clients))) < 2:
        raise ConfigError(
            f"deploy.secagg.enabled: a round chooses {chosen} robot (data.clients={clients}, "
            f"federated.fraction={fraction:g}); SecAgg+ needs 2 or more to hide each update"
        )
    if federated.dp.enabled and secagg.clipping_range < 1:
        raise ConfigError(
            f"deploy.secagg.clipping_range={secagg.clipping_range:g} with federated.dp: "
            "each robot's weight 1 (and adaptive clipping's +-1/2 bit) travels in its "
            "vector and would be clipped, so the sums' counts would be wrong; use 1 or more"
        )
    step = 2 * secagg.clipping_range / secagg.quantization_range  # one quantisation level
    if clients * secagg.max_samples * step >= 0.5:
        raise ConfigError(
            f"deploy.secagg.max_samples={secagg.max_samples}: with clipping_range="
            f"{secagg.clipping_range:g} and quantization_range={secagg.quantization_range} "
            f"the summed sample count of {clients} robots is off by up to "
            f"{clients * secagg.max_samples * step:.3g}, which cannot be rounded to the "
            "whole count: raise quantization_range or lower max_samples"
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


def _privacy_fits(config: ExperimentConfig) -> None:
    """Client-level DP (``federated.dp``) bounds what one client adds to a weighted sum:
    a statistic of the uploads (a median, Krum's choice) has no such bound; adaptive
    clipping's count noise must leave budget for the updates (over ``z / 2``: the count of
    centred bits, :func:`fedlgr.core.privacy.update_multiplier`); delta below 1 / clients."""
    dp, federated = config.federated.dp, config.federated
    if not dp.enabled:
        return
    if _aggregates_a_statistic(federated):
        raise ConfigError(
            f"federated.dp.clip={dp.clip:g} with federated.strategy={federated.strategy}: "
            "DP-FedAvg bounds one client's effect on the mean of clipped updates, and a "
            f"{federated.strategy} aggregate of the uploads has no such bound (one client "
            f"can move it arbitrarily far in L2); {mean_based()}"
        )
    clients = config.data.clients
    if dp.delta >= 1 / clients:
        raise ConfigError(
            f"federated.dp.delta={dp.delta:g}: must be below 1 / data.clients = "
            f"{1 / clients:g} (a delta of 1/N allows one client's data to be released)"
        )
    if dp.clipping == "adaptive" and dp.noise_multiplier > 0:
        count_std = dp.count_noise or federated.fraction * clients / 20
        if 2 * count_std <= dp.noise_multiplier:
            raise ConfigError(
                f"federated.dp.clipping=adaptive: the noise on the unclipped count "
                f"({count_std:g}{' = fraction x clients / 20' if not dp.count_noise else ''})"
                f" must be over federated.dp.noise_multiplier / 2 = "
                f"{dp.noise_multiplier / 2:g}, or it takes the whole privacy budget (one "
                "client moves the count of centred bits by 1/2: Andrew et al. 2021, Th. 1): "
                "set federated.dp.count_noise"
            )


def mean_based() -> str:
    """The way out of a refusal that needs a mean: the registered strategies that aggregate
    one (imports them all: only an error message asks)."""
    names = [name for name, method in STRATEGIES.items() if not method.load().needs_uploads]
    return f"use a mean-based strategy ({', '.join(names)})"


def _aggregates_a_statistic(federated) -> bool:
    """Is the strategy's aggregate a statistic of every upload (a median, Krum's choice)
    rather than a mean? Imports the strategy (torch): asked under DP or SecAgg only."""
    return STRATEGIES[federated.strategy].load().needs_uploads
