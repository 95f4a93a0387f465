"""Settings checks: the rules each section of a config follows (``model``, ``train``,
``federated``, ``runtime``, ``deploy``, ``tracking``, ``continual``, ``data``); those
across sections are in :mod:`.experiment`.

The config's dataclasses (:mod:`fedlgr.shell.config.settings`) call these from
``__post_init__``, so a config loaded from YAML and one built in code are checked alike;
each refusal is one line that names the setting, made by the generic validators of
:mod:`.values`. The bounds are fixed on purpose, and each message says why."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fedlgr.core.methods import CONTINUAL, SCOPES, STRATEGIES
from fedlgr.errors import ConfigError
from fedlgr.shell.checks.values import (
    betas,
    check_numbers,
    check_seed,
    check_settings,
    choice,
    epochs,
    format_bytes,
    nonnegative,
    positive,
)

if TYPE_CHECKING:
    from fedlgr.shell.config.data import DataConfig, NoiseConfig, TaskSpec
    from fedlgr.shell.config.settings import (
        ContinualConfig,
        DeployConfig,
        DPConfig,
        FaultsConfig,
        FederatedConfig,
        ModelConfig,
        RuntimeConfig,
        SecAggConfig,
        TrackingConfig,
        TrainConfig,
    )

ROOTS = ("auto", "mobilenet_v2", "mlp")
MLP_BLOCKS = ("linear_bn_relu", "linear")  # model.mlp_block: MLPRoot's block
PRECISIONS = ("32-true", "bf16-mixed", "16-mixed")
SERVER_EVAL = ("off", "on", "auto")
CONCURRENCY = ("auto", "sequential", "threads", "batched")
EVALUATE_MODES = ("with_next_round", "separate")  # deploy.evaluate
MODALITIES = ("image", "features")
PARTITIONS = ("iid", "dirichlet")
PARTITION_KEYS = ("task", "label")
BAD_IMAGE_POLICIES = ("error", "skip")

MAX_ROUNDS = 1_000_000
ROUNDS_BOUND = (
    f"at most {MAX_ROUNDS} rounds (a fixed bound: each round trains every client and logs to "
    f"MLflow, so at even 1 s a round {MAX_ROUNDS} rounds take 12 days)"
)
MAX_EXPERIMENT_NAME = 500  # MLflow's mlflow.utils.validation.MAX_EXPERIMENT_NAME_LENGTH
MAX_INTERVAL_S = 86_400  # heartbeat and system-metrics intervals (threading.Event.wait)
MAX_PER_MACHINE = 1024  # processes, torch threads or client threads on one machine
# The paper trains at 128 px with 10 copies of each scene per epoch.
MIN_IMAGE_SIZE, MAX_IMAGE_SIZE = 16, 4096
MAX_AUGMENT_COPIES = 1000


def rounds(setting: str, value: int) -> None:
    """A count of rounds: at least one, at most MAX_ROUNDS."""
    positive(setting, value)
    if value > MAX_ROUNDS:
        raise ConfigError(f"{setting}={value}: {ROUNDS_BOUND}")


def _method_settings(section: Any, family: str, registry: dict) -> None:
    """Every registered method's settings in ``section`` (a ``federated`` or ``continual``
    section), against the bounds their fields declare."""
    for m in registry.values():
        if m.settings is not None:
            check_settings(f"{family}.{m.key}", getattr(section, m.key))


# --------------------------------------------------------------------------- the sections


def check_model(model: ModelConfig) -> None:
    check_numbers("model.", model)
    choice("model.root", model.root, ROOTS)
    if model.width <= 0:
        raise ConfigError(f"model.width={model.width}: must be > 0")
    if model.weights == "imagenet" and model.width != 1.0:
        raise ConfigError(
            f"model.weights=imagenet needs model.width=1.0 (got {model.width}): "
            "the ImageNet weights exist only for the full-width MobileNetV2"
        )
    if not model.mlp_hidden or min(model.mlp_hidden) < 1:
        raise ConfigError(f"model.mlp_hidden={list(model.mlp_hidden)}: need >= 1 positive size")
    choice("model.mlp_block", model.mlp_block, MLP_BLOCKS)
    positive("model.top_hidden", model.top_hidden)


def check_train(train: TrainConfig) -> None:
    check_numbers("train.", train)
    epochs("train.epochs", train.epochs)
    positive("train.batch_size", train.batch_size)
    positive("train.eval_batch_size", train.eval_batch_size)
    if train.max_batches is not None:
        positive("train.max_batches", train.max_batches)
    for name in ("lr_root", "lr_top", "weight_decay"):
        nonnegative(f"train.{name}", getattr(train, name))
    betas("train.betas", train.betas)
    choice("train.precision", train.precision, PRECISIONS)


def check_federated(federated: FederatedConfig) -> None:
    check_numbers("federated.", federated)
    if not 0.0 < federated.fraction <= 1.0:
        raise ConfigError(
            f"federated.fraction={federated.fraction}: must be in (0, 1] (the share of the "
            "clients that train in a round; 1: all of them)"
        )
    if federated.norm_ratio != 0 and federated.norm_ratio < 1:
        raise ConfigError(
            f"federated.norm_ratio={federated.norm_ratio}: must be 0 (no check) or at least 1 "
            "(an update over this many times the round's median update norm is refused)"
        )
    choice("federated.strategy", federated.strategy, tuple(STRATEGIES))
    choice("federated.scope", federated.scope, tuple(SCOPES))
    rounds("federated.rounds", federated.rounds)
    choice("federated.server_eval", federated.server_eval, SERVER_EVAL)
    choice("federated.evaluate", federated.evaluate, EVALUATED)
    positive("federated.eval_clients", federated.eval_clients)
    positive("federated.eval_every", federated.eval_every)
    _method_settings(federated, "federated", STRATEGIES)


EVALUATED = ("all", "chosen", "sample")  # federated.evaluate
IDLE_CLIENTS = ("auto", "live", "memory", "disk")  # runtime.idle_clients

ATTACKS = ("sign_flip", "noise", "scale", "labels")


def check_faults(faults: FaultsConfig) -> None:
    check_numbers("federated.faults.", faults)
    for name, what in (("dropout", "drops out of"), ("straggler", "is late in")):
        value = getattr(faults, name)
        if not 0.0 <= value < 1.0:
            raise ConfigError(
                f"federated.faults.{name}={value}: must be in [0, 1) (the probability that a "
                f"chosen client {what} a round)"
            )
    if faults.byzantine < 0:
        raise ConfigError(f"federated.faults.byzantine={faults.byzantine}: must be 0 or more")
    choice("federated.faults.attack", faults.attack, ATTACKS)
    if faults.noise < 0:
        raise ConfigError(f"federated.faults.noise={faults.noise}: must be 0 or more")


CLIPPING = ("fixed", "adaptive")  # federated.dp.clipping


def check_dp(dp: DPConfig) -> None:
    check_numbers("federated.dp.", dp)
    for name in ("clip", "noise_multiplier", "count_noise", "target_epsilon"):
        nonnegative(f"federated.dp.{name}", getattr(dp, name))
    if not 0.0 < dp.delta < 1.0:
        raise ConfigError(f"federated.dp.delta={dp.delta}: must be in (0, 1)")
    choice("federated.dp.clipping", dp.clipping, CLIPPING)
    if not 0.0 < dp.quantile < 1.0:
        raise ConfigError(
            f"federated.dp.quantile={dp.quantile}: must be in (0, 1) (the share of updates "
            "that adaptive clipping aims to leave unclipped)"
        )
    if dp.clip_lr <= 0:
        raise ConfigError(f"federated.dp.clip_lr={dp.clip_lr}: must be over 0")
    if dp.target_epsilon > 0 and dp.noise_multiplier == 0:
        raise ConfigError(
            f"federated.dp.target_epsilon={dp.target_epsilon:g} needs noise: with "
            "federated.dp.noise_multiplier=0 epsilon is infinite from the first round"
        )


def check_runtime(runtime: RuntimeConfig) -> None:
    check_numbers("runtime.", runtime)
    choice("runtime.accelerator", runtime.accelerator, ("auto", "cpu", "gpu", "cuda"))
    choice("runtime.launcher", runtime.launcher, ("ddp", "ddp_spawn"))
    choice("runtime.concurrency", runtime.concurrency, CONCURRENCY)
    choice("runtime.idle_clients", runtime.idle_clients, IDLE_CLIENTS)
    if not runtime.idle_memory_mb >= 0:
        raise ConfigError(
            f"runtime.idle_memory_mb={runtime.idle_memory_mb}: must be 0 or more (MiB of idle "
            "clients' state held in memory before the rest goes to disk)"
        )
    positive("runtime.devices", runtime.devices)
    positive("runtime.num_nodes", runtime.num_nodes)
    for name in ("devices", "threads", "workers"):
        value = getattr(runtime, name)
        if value is not None and value > MAX_PER_MACHINE:
            raise ConfigError(
                f"runtime.{name}={value}: at most {MAX_PER_MACHINE} (a fixed bound, more "
                "than any machine's cores or GPUs: each is a process or a thread)"
            )
    # at least a second: a shorter wait gives up on the other processes before they answer
    if not 1 <= runtime.timeout_s <= 7 * 86400:
        raise ConfigError(
            f"runtime.timeout_s={runtime.timeout_s}: from 1 second to a week (604800)"
        )
    for name in ("threads", "workers"):
        if getattr(runtime, name) is not None:
            positive(f"runtime.{name}", getattr(runtime, name))


def check_deploy(deploy: DeployConfig) -> None:
    check_numbers("deploy.", deploy)
    if deploy.evaluate not in EVALUATE_MODES:
        raise ConfigError(
            f"deploy.evaluate={deploy.evaluate!r}: expected one of {', '.join(EVALUATE_MODES)}"
        )
    if deploy.min_clients is not None:
        positive("deploy.min_clients", deploy.min_clients)
    for name in ("join_timeout_s", "round_timeout_s"):
        if not getattr(deploy, name) > 0:
            raise ConfigError(f"deploy.{name}={getattr(deploy, name)}: must be > 0")


MODULUS = 2**32  # SecAgg+'s masks: sums of quantised values must stay below it


def check_secagg(secagg: SecAggConfig) -> None:
    """SecAgg+'s ranges (Flower's ``SecAggPlusWorkflow``): a sum of quantised values over
    up to 1024 robots stays below the masks' modulus 2^32."""
    check_numbers("deploy.secagg.", secagg)
    if not secagg.clipping_range > 0:
        raise ConfigError(f"deploy.secagg.clipping_range={secagg.clipping_range}: must be > 0")
    if not 2 <= secagg.quantization_range <= MODULUS // 1024:
        raise ConfigError(
            f"deploy.secagg.quantization_range={secagg.quantization_range}: must be in [2, "
            f"2^22] (1024 robots' quantised values must sum below SecAgg+'s modulus 2^32)"
        )
    positive("deploy.secagg.max_samples", secagg.max_samples)
    of = {"shares": "the round's robots", "threshold": "the shares"}
    for name, whole in of.items():
        if not 0 < getattr(secagg, name) <= 1:
            raise ConfigError(
                f"deploy.secagg.{name}={getattr(secagg, name)}: must be in (0, 1] (a share "
                f"of {whole})"
            )


def check_tracking(tracking: TrackingConfig) -> None:
    check_numbers("tracking.", tracking)
    if not tracking.experiment:
        raise ConfigError("tracking.experiment: must not be empty")
    if len(tracking.experiment) > MAX_EXPERIMENT_NAME:
        raise ConfigError(
            f"tracking.experiment: {len(tracking.experiment)} characters, MLflow allows at "
            f"most {MAX_EXPERIMENT_NAME} (mlflow.utils.validation.MAX_EXPERIMENT_NAME_LENGTH)"
        )
    for name, what in (("heartbeat_s", "beats"), ("system_metrics_s", "samples")):
        # at least a second: a shorter interval writes to the store thousands of times a second
        if not 1 <= getattr(tracking, name) <= MAX_INTERVAL_S:
            raise ConfigError(
                f"tracking.{name}={getattr(tracking, name)}: from 1 to {MAX_INTERVAL_S} "
                f"seconds (a day: a thread waits this long between two {what})"
            )
    if tracking.checkpoint < 0:
        raise ConfigError(f"tracking.checkpoint={tracking.checkpoint}: must be >= 0 (0: none)")
    positive("tracking.keep_checkpoints", tracking.keep_checkpoints)


def check_continual(continual: ContinualConfig) -> None:
    check_numbers("continual.", continual)
    choice("continual.method", continual.method, tuple(CONTINUAL))
    rounds("continual.rounds_per_task", continual.rounds_per_task)
    if continual.importance_batches is not None:
        positive("continual.importance_batches", continual.importance_batches)
    _method_settings(continual, "continual", CONTINUAL)
    _replay_layer(continual.lgr)
    if continual.method != "none" and not continual.tasks:
        raise ConfigError(
            f"continual.method={continual.method} needs a task schedule: set continual.tasks "
            "(e.g. [circle, arrow]) or use a Table II method name (method=FedRoot-EWC)"
        )


def _replay_layer(lgr: Any) -> None:
    """``continual.lgr.replay_layer=freeze`` replays the activations entering the root's
    last ``train_blocks`` blocks, which train with the top on real and replayed ones
    together: there is no drift to compensate there."""
    if lgr.replay_layer != "freeze":
        return
    at = "continual.lgr."
    wrong = [
        f"{at}{name}={value}"
        for name, value, ok in (
            ("train_blocks", lgr.train_blocks, bool(lgr.train_blocks)),
            ("schedule", lgr.schedule, lgr.schedule == "joint"),
            ("drift", lgr.drift, "compensate" not in lgr.drift),
        )
        if not ok
    ]
    if wrong:
        raise ConfigError(
            f"{at}replay_layer=freeze replays the activations entering the root's "
            "last train_blocks blocks, which train with the top on real and replayed "
            "ones together (no drift to compensate there): it needs train_blocks >= 1, "
            "schedule=joint and no compensation, not " + ", ".join(wrong)
        )


# --------------------------------------------------------------------------- data


def check_task(task: TaskSpec) -> None:
    check_numbers(f"data.tasks.{task.name}.", task)


def check_data(data: DataConfig) -> None:
    check_numbers("data.", data)
    check_seed("data.seed", data.seed)
    choice("data.modality", data.modality, MODALITIES)
    choice("data.partition", data.partition, PARTITIONS)
    choice("data.partition_key", data.partition_key, PARTITION_KEYS)
    choice("data.on_bad_image", data.on_bad_image, BAD_IMAGE_POLICIES)
    _image_size(data.image_size)
    if not 0.0 < data.test_fraction < 1.0:
        raise ConfigError(f"data.test_fraction={data.test_fraction}: must be between 0 and 1")
    if data.clients < 1:
        raise ConfigError(f"data.clients={data.clients}: need at least 1 client")
    if data.dirichlet_alpha <= 0:
        raise ConfigError(f"data.dirichlet_alpha={data.dirichlet_alpha}: must be > 0")
    _augment_copies(data.augment_copies)
    if data.modality == "image" and data.noise != type(data.noise)():
        raise ConfigError(
            "data.noise: the descriptors' noise, for data.modality=features; images are "
            "flipped and rotated instead (data.augment, data.augment_copies)"
        )
    _task_names([t.name for t in data.tasks])
    if data.crop is not None:
        _crop(data.crop)


def check_noise(noise: NoiseConfig) -> None:
    check_numbers("data.noise.", noise)
    nonnegative("data.noise.std", noise.std)


def _image_size(size: int) -> None:
    if size < MIN_IMAGE_SIZE:
        raise ConfigError(f"data.image_size={size}: must be at least {MIN_IMAGE_SIZE}")
    if size > MAX_IMAGE_SIZE:
        raise ConfigError(
            f"data.image_size={size}: at most {MAX_IMAGE_SIZE} (a fixed bound: each scene "
            f"takes 3 x size^2 bytes in the decoded image store and 12 x size^2 as float32 in "
            f"a batch, {format_bytes(3 * size**2)} and {format_bytes(12 * size**2)} here; "
            "the paper trains at 128 px)"
        )


def _augment_copies(copies: int) -> None:
    positive("data.augment_copies", copies)
    if copies > MAX_AUGMENT_COPIES:
        raise ConfigError(
            f"data.augment_copies={copies}: at most {MAX_AUGMENT_COPIES} (a fixed bound: an "
            "augmented epoch shows each training scene this many times, and its shuffled "
            f"order takes 24 bytes per showing, {format_bytes(24 * copies)} per scene here; "
            "the paper uses 10)"
        )


def _task_names(names: list[str]) -> None:
    if not names:
        raise ConfigError("data.tasks: need at least one task")
    if len(set(names)) != len(names):
        raise ConfigError(f"data.tasks: task names must be unique, got {names}")


def _crop(crop: Any) -> None:
    """``[left, top, right, bottom]`` source pixels, each >= 0 or null for an image edge."""
    box = tuple(crop)
    if len(box) != 4 or not all(v is None or (isinstance(v, int) and v >= 0) for v in box):
        raise ConfigError(
            f"data.crop={list(crop)}: must be [left, top, right, bottom] "
            "pixel positions (>= 0) or null for an image edge"
        )
    left, top, right, bottom = box
    if left is not None and right is not None and right <= left:
        raise ConfigError(f"data.crop={list(crop)}: right ({right}) must exceed left ({left})")
    if top is not None and bottom is not None and bottom <= top:
        raise ConfigError(f"data.crop={list(crop)}: bottom ({bottom}) must exceed top ({top})")
