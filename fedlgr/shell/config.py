"""Experiment settings: typed, validated dataclasses filled from YAML and ``key=value``.

The dataclasses are the single source of truth; OmegaConf merges, in order, the defaults,
the files a config ``includes`` (paths relative to ``conf/``, recursively), the config
file itself and the command-line overrides, checks every key and type against the
dataclasses, and builds them (so each ``__post_init__`` validates its own settings with
messages that name the setting). ``method=FedRootProx`` is shorthand for
``federated.strategy=prox federated.scope=root``.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fedlgr.core.data.columns import FEATURE_COLUMNS
from fedlgr.core.methods import CONTINUAL, FCL_METHODS, METHODS, SCOPES, STRATEGIES, method_name
from fedlgr.errors import ConfigError
from fedlgr.shell.checks.paths import not_a_file
from fedlgr.shell.checks.values import betas as _betas
from fedlgr.shell.checks.values import (
    check_numbers,
    check_seed,
    check_settings,
    format_bytes,
    machine_memory,
)
from fedlgr.shell.checks.values import choice as _choice
from fedlgr.shell.checks.values import epochs as _epochs
from fedlgr.shell.checks.values import positive as _positive
from fedlgr.shell.data.config import DataConfig
from fedlgr.shell.tracking.uri import mask_password


def _shipped(folder: str) -> Path:
    """``conf/`` or ``sweeps/``: the copy a wheel ships inside the package (pyproject's
    ``force-include``, for ``pip install`` / ``uv tool install``), else the checkout's, next
    to the package (a clone, an editable install)."""
    package = Path(__file__).resolve().parents[1]  # fedlgr/
    return package / folder if (package / folder).is_dir() else package.parent / folder


CONF_DIR = _shipped("conf")
SWEEPS_DIR = _shipped("sweeps")


def find_config(name: str | Path) -> Path:
    """A config file as given, else the shipped one it names relative to ``conf/``
    (``debug/fast.yaml``, ``conf/debug/fast.yaml`` outside a checkout, ``.yaml`` optional);
    unchanged when neither exists (loading it then names the missing file)."""
    path = Path(name)
    if path.is_file() or path.is_absolute():
        return path
    inside = Path(*path.parts[1:]) if path.parts[:1] == ("conf",) else path
    for candidate in (CONF_DIR / inside, (CONF_DIR / inside).with_suffix(".yaml")):
        if candidate.is_file():
            return candidate
    return path


ROOTS = ("auto", "mobilenet_v2", "mlp")
PRECISIONS = ("32-true", "bf16-mixed", "16-mixed")


# Bounds on purpose, each refused with its reason.
MAX_ROUNDS = 1_000_000
_ROUNDS_BOUND = (
    f"at most {MAX_ROUNDS} rounds (a fixed bound: each round trains every client and logs to "
    f"MLflow, so at even 1 s a round {MAX_ROUNDS} rounds take 12 days)"
)
MAX_EXPERIMENT_NAME = 500  # MLflow's mlflow.utils.validation.MAX_EXPERIMENT_NAME_LENGTH
MAX_INTERVAL_S = 86_400  # heartbeat and system-metrics intervals (threading.Event.wait)
MOBILENET_V2_NUMBERS = 2_258_036  # parameters and buffers of torchvision's features, width 1
MOBILENET_V2_BLOCKS = 19  # its features' blocks (Root.blocks(); a test checks the model)


@dataclass(frozen=True)
class ModelConfig:
    """The scholar: a root (MobileNetV2 features + pool, or an MLP for the features
    modality) and a top (BN -> 32 -> BN -> 8), SPEC 3."""

    root: str = "auto"  # auto: mobilenet_v2 for images, mlp for features
    weights: str = "none"  # imagenet | none | path to a state dict file
    width: float = 1.0  # MobileNetV2 width multiplier (tests use a tiny one)
    mlp_hidden: tuple[int, ...] = (256, 256)
    top_hidden: int = 32
    output_bias: float = 3.0  # initial output bias: the middle of the Likert scale
    channels_last: bool = True  # faster convolutions on CPU and GPU

    def __post_init__(self) -> None:
        check_numbers("model.", self)
        _choice("model.root", self.root, ROOTS)
        if self.width <= 0:
            raise ConfigError(f"model.width={self.width}: must be > 0")
        if self.weights == "imagenet" and self.width != 1.0:
            raise ConfigError(
                f"model.weights=imagenet needs model.width=1.0 (got {self.width}): "
                "the ImageNet weights exist only for the full-width MobileNetV2"
            )
        if not self.mlp_hidden or min(self.mlp_hidden) < 1:
            raise ConfigError(f"model.mlp_hidden={list(self.mlp_hidden)}: need >= 1 positive size")
        if self.top_hidden < 1:
            raise ConfigError(f"model.top_hidden={self.top_hidden}: must be >= 1")


@dataclass(frozen=True)
class TrainConfig:
    """Local training of each client, and evaluation."""

    epochs: int = 10  # local epochs per round
    batch_size: int = 16
    lr_root: float = 1e-3
    lr_top: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.999)
    max_batches: int | None = None  # cap per epoch (fast dev runs)
    reset_optimizer: bool = False  # a fresh Adam state every round instead of the client's own
    eval_batch_size: int = 128
    # The reference code averages per-batch RMSE/PCC over test batches of 16 (biased):
    # offered for comparison only.
    compat_batch_metrics: bool = False
    precision: str = "32-true"

    def __post_init__(self) -> None:
        check_numbers("train.", self)
        _epochs("train.epochs", self.epochs)
        _positive("train.batch_size", self.batch_size)
        _positive("train.eval_batch_size", self.eval_batch_size)
        if self.max_batches is not None:
            _positive("train.max_batches", self.max_batches)
        for name in ("lr_root", "lr_top"):
            if getattr(self, name) < 0:
                raise ConfigError(f"train.{name}={getattr(self, name)}: must be >= 0")
        _betas("train.betas", self.betas)
        _choice("train.precision", self.precision, PRECISIONS)


SERVER_EVAL = ("off", "on", "auto")
SERVER_EVAL_ALIASES = {"true": "on", "false": "off"}


def _with_sections(base: type, family: str, registry: dict) -> type:
    """``base`` plus one field per registered method with settings (``federated.prox``,
    ``continual.lgr``), each that method's settings dataclass. Built from the registry
    (``fedlgr.core.methods``) so that a new method's settings need no edit here."""
    sections = [
        (m.key, m.settings, field(default_factory=m.settings))
        for m in registry.values()
        if m.settings is not None
    ]
    made = dataclasses.make_dataclass(
        base.__name__.lstrip("_"), sections, bases=(base,), frozen=True
    )
    made.__module__, made.__doc__ = __name__, base.__doc__
    made.__qualname__ = made.__name__
    return made


def _check_sections(config, family: str, registry: dict) -> None:
    """Every registered method's settings in ``config`` (a ``federated`` or ``continual``
    section), against the bounds their fields declare."""
    for m in registry.values():
        if m.settings is not None:
            check_settings(f"{family}.{m.key}", getattr(config, m.key))


@dataclass(frozen=True)
class _FederatedConfig:
    """What is shared (scope), how it is aggregated (strategy, with each strategy's
    settings under ``federated.<strategy>``: ``federated.prox.mu``), SPEC 4.1."""

    strategy: str = "avg"
    scope: str = "full"
    rounds: int = 10
    # The server scores the global model on the test scenes every round (and before round
    # 1): server/test/*. off | on (full scope only: FedRoot keeps the top on the clients) |
    # auto (where the server holds a whole model: full-scope methods, as the paper's code).
    server_eval: str = "off"
    # The share of the clients that train in each round (Flower's fraction_train): all at
    # 1; else max(1, round(fraction x clients)) drawn from the run's seed each round. The
    # others keep their state and are still evaluated.
    fraction: float = 1.0

    def __post_init__(self) -> None:
        check_numbers("federated.", self)
        if not 0.0 < self.fraction <= 1.0:
            raise ConfigError(
                f"federated.fraction={self.fraction}: must be in (0, 1] (the share of the "
                "clients that train in a round; 1: all of them)"
            )
        _choice("federated.strategy", self.strategy, tuple(STRATEGIES))
        _choice("federated.scope", self.scope, tuple(SCOPES))
        _rounds("federated.rounds", self.rounds)
        # true/false as YAML or the command line give them: on/off
        value = SERVER_EVAL_ALIASES.get(str(self.server_eval).lower(), self.server_eval)
        object.__setattr__(self, "server_eval", value)
        _choice("federated.server_eval", self.server_eval, SERVER_EVAL)
        _check_sections(self, "federated", STRATEGIES)

    @property
    def method(self) -> str:
        return method_name(self.strategy, self.scope)

    @property
    def server_evaluates(self) -> bool:
        """Does the server score the global model (``server_eval``)?"""
        return self.server_eval == "on" or (self.server_eval == "auto" and self.scope == "full")

    @property
    def settings(self):
        """The strategy's settings (``federated.<strategy>``), None where it has none."""
        return getattr(self, STRATEGIES[self.strategy].section, None)


FederatedConfig = _with_sections(_FederatedConfig, "federated", STRATEGIES)


CONCURRENCY = ("auto", "sequential", "threads", "batched")


MAX_PER_MACHINE = 1024  # processes, torch threads or client threads on one machine


@dataclass(frozen=True)
class RuntimeConfig:
    """Where the clients run: one process by default, or sharded over processes/nodes."""

    accelerator: str = "auto"  # auto | cpu | gpu
    devices: int = 1  # processes per node; clients are sharded over all processes
    num_nodes: int = 1
    launcher: str = "ddp"  # ddp (re-runs the command per process) | ddp_spawn
    threads: int | None = None  # torch threads per process (default: cores / processes)
    # How a process's clients train (docs/runtimes.md): one after another
    # (sequential), side by side in threads that split the process's torch threads
    # (threads), or stacked into one model (batched, for a GPU); auto: threads on CPU
    # where a process has several clients and threads, else sequential.
    concurrency: str = "auto"
    workers: int | None = None  # clients at once with threads (default: min(clients, threads))
    progress: bool = True
    # How long a process of a multi-process run waits for the others: for all of them to
    # join at the start (a node never started), and at each exchange of a round (torch's
    # default, 30 min, lets a slow process's clients finish their round).
    timeout_s: float = 1800.0

    def __post_init__(self) -> None:
        check_numbers("runtime.", self)
        _choice("runtime.accelerator", self.accelerator, ("auto", "cpu", "gpu", "cuda"))
        _choice("runtime.launcher", self.launcher, ("ddp", "ddp_spawn"))
        _choice("runtime.concurrency", self.concurrency, CONCURRENCY)
        _positive("runtime.devices", self.devices)
        _positive("runtime.num_nodes", self.num_nodes)
        for name in ("devices", "threads", "workers"):
            value = getattr(self, name)
            if value is not None and value > MAX_PER_MACHINE:
                raise ConfigError(
                    f"runtime.{name}={value}: at most {MAX_PER_MACHINE} (a fixed bound, more "
                    "than any machine's cores or GPUs: each is a process or a thread)"
                )
        if not 1 <= self.timeout_s <= 7 * 86400:  # 0.001 was taken (z14)
            raise ConfigError(
                f"runtime.timeout_s={self.timeout_s}: from 1 second to a week (604800)"
            )
        for name in ("threads", "workers"):
            if getattr(self, name) is not None:
                _positive(f"runtime.{name}", getattr(self, name))

    @property
    def world_size(self) -> int:
        return self.devices * self.num_nodes


EVALUATE_MODES = ("with_next_round", "separate")  # deploy.evaluate


@dataclass(frozen=True)
class DeployConfig:
    """Real robots behind a Flower SuperLink (``fedlgr deploy``; docs/deployment.md)."""

    min_clients: int | None = None  # replies a round needs to go on (default: half, >= 1)
    join_timeout_s: float = 300.0  # how long round 1 waits for data.clients robots to join
    round_timeout_s: float = 600.0  # how long the server waits for replies in one exchange
    # with_next_round: a robot evaluates the new global tensors at the start of the next
    # round's training message (one exchange per round, one last evaluate message);
    # separate: a train and an evaluate exchange every round.
    evaluate: str = "with_next_round"
    # the roster file on the SuperLink's machine (fedlgr deploy node-key writes it): only
    # its robots take part, each in its slot; "none": any node that joins (no SuperNode
    # authentication, --insecure test machines only)
    roster: str | None = None

    def __post_init__(self) -> None:
        check_numbers("deploy.", self)
        if self.evaluate not in EVALUATE_MODES:
            raise ConfigError(
                f"deploy.evaluate={self.evaluate!r}: expected one of {', '.join(EVALUATE_MODES)}"
            )
        if self.min_clients is not None:
            _positive("deploy.min_clients", self.min_clients)
        for name in ("join_timeout_s", "round_timeout_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"deploy.{name}={getattr(self, name)}: must be > 0")


@dataclass(frozen=True)
class TrackingConfig:
    """MLflow: local sqlite store by default, or a server (``tracking.uri``)."""

    enabled: bool = True
    uri: str | None = None  # default: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db
    experiment: str = "fedlgr"
    run_name: str | None = None  # default: the method and setting, e.g. FedAvg-2c-noaug
    checkpoint: int = 1  # a checkpoint every N rounds (and after the last); 0: none
    keep_checkpoints: int = 2  # the newest K are kept while the run goes on
    checkpoint_dir: str | None = None  # default: checkpoints/ next to a sqlite store, else ./
    heartbeat_s: float = 30.0  # a live run's tag fedlgr.heartbeat is never older than this
    system_metrics: bool = True  # MLflow's system metrics (CPU, memory, GPU) of the machine
    system_metrics_s: float = 10.0  # seconds between two samples of them
    # Per-client and per-action metrics in MLflow too (results.csv always has them): 112
    # instead of 16 metrics for 2 clients, which bury the headline ones in MLflow's UI.
    detail_metrics: bool = False

    def __post_init__(self) -> None:
        check_numbers("tracking.", self)
        if not self.experiment:
            raise ConfigError("tracking.experiment: must not be empty")
        if len(self.experiment) > MAX_EXPERIMENT_NAME:
            raise ConfigError(
                f"tracking.experiment: {len(self.experiment)} characters, MLflow allows at most "
                f"{MAX_EXPERIMENT_NAME} (mlflow.utils.validation.MAX_EXPERIMENT_NAME_LENGTH)"
            )
        for name, what in (("heartbeat_s", "beats"), ("system_metrics_s", "samples")):
            # at least a second: 0.0001 was taken (seventh fault sweep, z10/z13), a write
            # to the store 10,000 times a second
            if not 1 <= getattr(self, name) <= MAX_INTERVAL_S:
                raise ConfigError(
                    f"tracking.{name}={getattr(self, name)}: from 1 to {MAX_INTERVAL_S} "
                    f"seconds (a day: a thread waits this long between two {what})"
                )
        if self.checkpoint < 0:
            raise ConfigError(f"tracking.checkpoint={self.checkpoint}: must be >= 0 (0: none)")
        _positive("tracking.keep_checkpoints", self.keep_checkpoints)


@dataclass(frozen=True)
class _ContinualConfig:
    """Federated continual learning (SPEC 4.2): a task schedule and a CL method, with each
    method's settings under ``continual.<method>`` (``continual.ewc.lambda_``).

    ``tasks`` lists task names of ``data.tasks`` in training order; empty means plain FL
    (all training scenes at once, ``federated.rounds`` rounds). With tasks, each task is
    trained for ``rounds_per_task`` rounds and ``federated.rounds`` is not used.
    """

    tasks: tuple[str, ...] = ()
    rounds_per_task: int = 5
    method: str = "none"  # a key of fedlgr.core.methods.CONTINUAL: none | ewc | ... | lgr
    importance_batches: int | None = None  # batches for Fisher / MAS importance (None: all)
    freeze_root_bn: bool = False  # root BatchNorm statistics frozen from task 2 (not FedLGR:
    # continual.lgr.freeze_root_bn)

    def __post_init__(self) -> None:
        object.__setattr__(self, "tasks", tuple(self.tasks))
        check_numbers("continual.", self)
        _choice("continual.method", self.method, tuple(CONTINUAL))
        _rounds("continual.rounds_per_task", self.rounds_per_task)
        if self.importance_batches is not None:
            _positive("continual.importance_batches", self.importance_batches)
        _check_sections(self, "continual", CONTINUAL)
        _check_replay_layer(self.lgr)
        if self.method != "none" and not self.tasks:
            raise ConfigError(
                f"continual.method={self.method} needs a task schedule: set continual.tasks "
                "(e.g. [circle, arrow]) or use a Table II method name (method=FedRoot-EWC)"
            )

    @property
    def settings(self):
        """The method's settings (``continual.<method>``), None where it has none."""
        return getattr(self, CONTINUAL[self.method].section, None)


ContinualConfig = _with_sections(_ContinualConfig, "continual", CONTINUAL)


def _check_replay_layer(lgr) -> None:
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


@dataclass(frozen=True)
class ExperimentConfig:
    method: str | None = None  # paper name; sets federated.strategy and federated.scope
    seed: int = 0  # model initialisation, batch order, augmentation (data.seed: the split)
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    federated: FederatedConfig = field(default_factory=FederatedConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    continual: ContinualConfig = field(default_factory=ContinualConfig)
    deploy: DeployConfig = field(default_factory=DeployConfig)

    def __post_init__(self) -> None:
        check_numbers("", self)
        check_seed("seed", self.seed)
        if self.continual.tasks and self.total_rounds > MAX_ROUNDS:
            raise ConfigError(
                f"continual.rounds_per_task={self.continual.rounds_per_task} x "
                f"{len(self.continual.tasks)} tasks = {self.total_rounds} rounds: {_ROUNDS_BOUND}"
            )
        cl = CONTINUAL[self.continual.method]
        if self.federated.scope not in cl.scopes:
            raise ConfigError(
                f"continual.method={cl.key} ({method_name('avg', cl.scopes[0], cl.key)}) works "
                f"with federated.scope={' or '.join(cl.scopes)} only: set "
                f"federated.scope={cl.scopes[0]}"
            )
        if self.federated.server_eval == "on" and self.federated.scope == "root":
            raise ConfigError(
                f"federated.server_eval=on: {self.method_name} shares the root only and "
                "keeps each top on its client, so the server holds no whole model to "
                "evaluate; server evaluation is for full-scope methods (FedAvg, FedBN, "
                "FedProx, FedOpt, FedDistill and their CL variants; 'auto' turns it on "
                "for those only)"
            )
        if self.method is not None and self.method != self.method_name:
            raise ConfigError(f"method={self.method} disagrees with federated/continual settings")
        known = [t.name for t in self.data.tasks]
        unknown = [t for t in self.continual.tasks if t not in known]
        if unknown:
            raise ConfigError(f"continual.tasks: unknown task(s) {unknown}; data.tasks has {known}")
        root = self.root_kind
        if self.data.modality == "features" and root != "mlp":
            raise ConfigError(
                f"model.root={self.model.root} reads images, but data.modality=features: "
                "use model.root=mlp (or auto)"
            )
        if self.runtime.world_size > self.data.clients:
            raise ConfigError(
                f"runtime.devices x runtime.num_nodes = {self.runtime.world_size} processes for "
                f"data.clients={self.data.clients}: every process needs at least one client"
            )
        if (self.deploy.min_clients or 0) > self.data.clients:
            raise ConfigError(
                f"deploy.min_clients={self.deploy.min_clients} exceeds "
                f"data.clients={self.data.clients}"
            )
        if self.data.modality == "image" and root == "mlp":
            raise ConfigError("model.root=mlp reads the descriptors: set data.modality=features")
        self._check_train_blocks()
        self._check_model_fits()

    def _check_train_blocks(self) -> None:
        """``continual.lgr.train_blocks=k`` trains the root's last k blocks: more blocks than
        the root has would train it whole without a word."""
        k = self.continual.lgr.train_blocks
        if k is None or self.continual.method != "lgr" or not self.continual.tasks:
            return
        # Root.blocks() (fedlgr.core.models.scholar): MobileNetV2's features, an MLP's layers
        mlp = self.root_kind == "mlp"
        blocks = len(self.model.mlp_hidden) if mlp else MOBILENET_V2_BLOCKS
        if k > blocks:
            what = f"model.mlp_hidden={list(self.model.mlp_hidden)}" if mlp else "MobileNetV2"
            raise ConfigError(
                f"continual.lgr.train_blocks={k}: the root ({what}) has {blocks} block"
                f"{'' if blocks == 1 else 's'}; at most {blocks} (null: the whole root trains)"
            )

    def _check_model_fits(self) -> None:
        """Refuse a scholar too large to train in this machine's memory, before it is built."""
        m = self.model
        if self.root_kind == "mlp":
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

    @property
    def root_kind(self) -> str:
        if self.model.root != "auto":
            return self.model.root
        return "mlp" if self.data.modality == "features" else "mobilenet_v2"

    @property
    def continual_learning(self) -> bool:
        """Is there a task schedule (FCL) rather than all data at once (FL)?"""
        return bool(self.continual.tasks)

    @property
    def method_name(self) -> str:
        f, c = self.federated, self.continual
        return method_name(f.strategy, f.scope, c.method if c.tasks else None)

    @property
    def total_rounds(self) -> int:
        c = self.continual
        return len(c.tasks) * c.rounds_per_task if c.tasks else self.federated.rounds

    @property
    def run_name(self) -> str:
        if self.tracking.run_name:
            return self.tracking.run_name
        aug = "aug" if self.data.augment else "noaug"
        return f"{self.method_name}-{self.data.clients}c-{aug}"


def _rounds(setting: str, value: int) -> None:
    _positive(setting, value)
    if value > MAX_ROUNDS:
        raise ConfigError(f"{setting}={value}: {_ROUNDS_BOUND}")


# --------------------------------------------------------------------------- loading

# The ``${...}`` a config file or override may hold (docs/methods.md, "Running experiments"): a
# reference to another setting, or an environment variable whose name starts with
# FEDLGR_ (optionally with a default). Everything else - other variables, oc.decode,
# oc.create, oc.select, oc.dict.*, nested interpolations - is refused before anything
# is resolved; ``\${`` stays a literal ``${``.
_REFERENCE = r"\.*[A-Za-z_][\w-]*(?:\.[\w-]+|\[\d+\])*"
_FEDLGR_ENV = r"oc\.env:FEDLGR_\w+(?:,[\w ./:@+-]*)?"
_ALLOWED = rf"\$\{{(?:{_REFERENCE}|{_FEDLGR_ENV})\}}"
_POLICY = (
    "a config's ${...} may name another setting (${data.clients}) or an environment "
    "variable FEDLGR_* (${oc.env:FEDLGR_DATA}), nothing else (docs/methods.md, "
    "'Running experiments')"
)


def yaml_reason(err: Exception) -> str:
    """Why OmegaConf's loader refused a YAML file, in one line: ``not valid YAML (...)`` or
    ``too large: ...``. Its limit on the nodes of
    one file (10,000, against alias bombs) names aliases and how to raise it, whether or
    not the file has an alias (the sixth fault sweep: a file of 200,000 plain keys); that
    is said as what it is, with no advice to lift a safety limit."""
    first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    found = re.search(r"YAML node expansion exceeds the configured limit of (\d+)", first)
    if found:
        return (
            f"too large: over {int(found.group(1)):,} YAML nodes (keys, values and list "
            "items), more than OmegaConf reads from one file (a config holds a few hundred)"
        )
    return f"not valid YAML ({first})"


MAX_NESTING = 50  # levels of a config file; fedlgr's own nest 4 at most (at 90 levels of
# mappings OmegaConf's own recursion gave up: the seventh fault sweep's re-check, u43)


def _check_nesting(path: Path) -> None:
    """A file nested deeper than MAX_NESTING levels is one line. OmegaConf composes YAML
    with libyaml's recursive C code, which crashed the process (SIGSEGV, no word) on
    100,000 nested ``[`` (the sixth fault sweep, n17); libyaml's event parser keeps its own
    stack, so the levels are counted from its events first (microseconds for a config)."""
    import yaml

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    opened = (yaml.MappingStartEvent, yaml.SequenceStartEvent)
    closed = (yaml.MappingEndEvent, yaml.SequenceEndEvent)
    depth = 0
    try:
        with path.open("rb") as stream:
            for event in yaml.parse(stream, Loader=loader):
                if isinstance(event, opened):
                    depth += 1
                    if depth > MAX_NESTING:
                        line = event.start_mark.line + 1
                        raise ConfigError(
                            f"{path}: nested over {MAX_NESTING} levels deep (line {line}); "
                            "a config nests a few"
                        )
                elif isinstance(event, closed):
                    depth -= 1
    except (yaml.YAMLError, OSError, UnicodeDecodeError):
        return  # said with its reason by the load that follows


def _read_layers(path: Path, seen: tuple[Path, ...] = ()) -> list[Any]:
    """The YAML at ``path`` preceded by what it includes, each as an OmegaConf node."""
    from omegaconf import OmegaConf

    # a broken link, or a path under a FIFO or a file (e50, e147): named, not "not found"
    if not path.exists() and (why := not_a_file(path)):
        raise ConfigError(f"{path.absolute()}: {why}")
    if path.exists() and not path.is_file() and not path.is_dir():
        # /dev/stdin, before it resolves to /proc/PID/fd/pipe:[N], which is no file (u37)
        raise ConfigError(f"{path.absolute()}: not a regular file (a device, pipe or socket)")
    path = path.resolve()
    if path in seen:
        raise ConfigError(f"{path}: includes itself (via {' -> '.join(p.name for p in seen)})")
    if path.is_dir():
        raise ConfigError(f"{path}: a folder, not a config file (name a .yaml file in it)")
    if path.exists() and not path.is_file():  # /dev/zero, a FIFO (seventh fault sweep)
        raise ConfigError(f"{path}: not a regular file (a device, pipe or socket)")
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    _check_nesting(path)
    try:
        node = OmegaConf.load(path)
    except Exception as err:
        raise ConfigError(f"{path}: {yaml_reason(err)}") from err
    if node is None or not OmegaConf.is_dict(node):
        raise ConfigError(f"{path}: expected a mapping of settings at the top level")
    if len(node) == 0:  # an empty file would run every default without a word
        raise ConfigError(f"{path}: holds no settings (an empty file); give a config that does")
    if any(not SETTING_NAME.fullmatch(str(key)) for key in node):
        # e.g. a text file named as a config or a sweep's base: its text is not echoed
        raise ConfigError(
            f"{path}: not a config file: its top level is not `setting: value` lines "
            "(a setting name is letters, digits, _ and .)"
        )
    written = _plain(node)  # nothing resolved
    includes = written.get("includes") or []
    if "includes" in written:
        del node["includes"]
    layers: list[Any] = []
    for inc in includes if isinstance(includes, list) else [includes]:
        if "${" in str(inc):
            raise ConfigError(f"{path}: includes: {inc!r}: name the file (no ${{...}} here)")
        layers += _read_layers(_included(Path(str(inc)), path), (*seen, path))
    return [*layers, (path, node)]


def _included(name: Path, including: Path) -> Path:
    """The file ``includes: [NAME]`` in ``including`` names: NAME.yaml (or NAME if it ends
    in .yaml/.yml, or NAME itself if only that exists), relative to conf/, else to the
    including file. ``with_suffix`` replaced a suffix: ``includes: [cfg.fifo]`` was said
    not to exist as cfg.yaml, ``/dev/zero`` as /dev/zero.yaml (the eighth fault sweep,
    u38, u39)."""
    names = [name] if name.suffix in (".yaml", ".yml") else [name.with_name(f"{name.name}.yaml")]
    names += [name] if name not in names else []
    folders = [Path("/")] if name.is_absolute() else [CONF_DIR, including.parent]
    candidates = [folder / n for n in names for folder in folders]
    return next((c for c in candidates if os.path.lexists(c)), candidates[len(folders) - 1])


def load_config(
    path: Path | str | None = None, overrides: list[str] | tuple[str, ...] = ()
) -> ExperimentConfig:
    """Merge the defaults, ``path`` (with its includes) and ``overrides`` (``key=value``).
    ``${...}`` is checked against ``_ALLOWED`` in every layer before anything resolves."""
    layers = _read_layers(Path(path)) if path is not None else []
    bad = [o for o in overrides if "=" not in o or o.startswith("=")]
    if bad:
        raise ConfigError(f"override {bad[0]!r}: expected key=value (e.g. federated.rounds=5)")
    layers = [*layers, ("command line", _dotlist(overrides))]
    layers = [(source, _renamed(source, node)) for source, node in layers]
    interpolated: dict[str, tuple[Any, str]] = {}
    for source, node in layers:
        interpolated.update(check_interpolations(source, node))
    return _build(layers, interpolated)


def config_from_data(data: Any, source: str) -> ExperimentConfig:
    """A config received as data (a robot's copy of the server's resolved config,
    :func:`to_yaml`): settings only, checked by :func:`check_data`."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    check_data(data, source)
    try:
        node = OmegaConf.create(data)
    except OmegaConfBaseException as err:
        raise ConfigError(f"{source}: {_omegaconf_message(err)}") from None
    return _build([(source, node)], {})


def check_data(data: Any, source: str) -> None:
    """Refuse what would make plain settings read or resolve anything: ``includes`` and
    any ``${`` (in a key or a value). The messages name the setting, never a value."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of settings at the top level")
    if "includes" in data:
        raise ConfigError(f"{source}: includes: refused (a config sent as data reads no files)")
    for key, value in _strings(data, keys=True):
        if "${" in value:
            raise ConfigError(
                f"{source}: {key}: holds ${{...}}, which a config sent as data may not "
                "(it is resolved where it was written)"
            )


def _deprecated_names() -> dict[tuple[str, str], str]:
    """``(section, old flat name) -> new name`` for the method settings that lived in
    ``federated``/``continual`` as prefixed fields up to fedlgr 0.x (``continual.lgr_hidden``
    is ``continual.lgr.hidden``, ``federated.server_lr`` is ``federated.opt.lr``). They are
    read, with a deprecation line, for one more release."""
    old = {("federated", f"server_{f}"): f"opt.{f}" for f in ("lr", "betas", "tau")}
    for section, registry, keys in (
        ("federated", STRATEGIES, ("prox", "distill")),
        ("continual", CONTINUAL, ("ewc", "si", "mas", "nr", "lgr")),
    ):
        for key in keys:
            for f in dataclasses.fields(registry[key].settings):
                old[(section, f"{key}_{f.name.rstrip('_')}")] = f"{key}.{f.name}"
    return old


DEPRECATED = _deprecated_names()


def _renamed(source: Any, node):
    """The layer with the deprecated flat method settings moved to their sections."""
    from omegaconf import OmegaConf

    values = _plain(node)
    moved = []
    for section in ("federated", "continual"):
        here = values.get(section) if isinstance(values, dict) else None
        if not isinstance(here, dict):
            continue
        for name in [n for n in here if (section, n) in DEPRECATED]:
            new = DEPRECATED[(section, name)]
            group, _, leaf = new.partition(".")
            target = here.setdefault(group, {})
            if not isinstance(target, dict):
                continue  # e.g. continual.lgr=5: the merge names the bad value
            if leaf in target:
                raise ConfigError(
                    f"{source}: {section}.{name} and {section}.{new} are one setting (the "
                    f"first is its deprecated name), given twice: keep {section}.{new}"
                )
            target[leaf] = here.pop(name)
            moved.append(f"{section}.{name} is now {section}.{new}")
    if not moved:
        return node
    print(
        f"fedlgr: {source}: deprecated setting names, read for one more release: "
        + "; ".join(moved),
        file=sys.stderr,
    )
    return OmegaConf.create(values)


SETTING_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.]{0,99}")


def _container_mismatch(merged, written: dict, prefix: str = "") -> str | None:
    """The setting given a mapping where a list goes, or a list where a section goes: what
    OmegaConf's merge refuses with a bare ``TypeError`` (the author's own fault sweep:
    ``train.betas: {a: 1}`` was a traceback)."""
    from omegaconf import DictConfig, ListConfig, OmegaConf
    from omegaconf.tupleconfig import TupleConfig

    for key, value in written.items():
        name = f"{prefix}{key}"
        target = OmegaConf.select(merged, name, default=None, throw_on_missing=False)
        if isinstance(value, dict) and isinstance(target, ListConfig | TupleConfig):
            return f"{name}: a list goes here, not a mapping ({_short(value)})"
        if isinstance(value, list) and isinstance(target, DictConfig):
            return f"{name}: a section of settings goes here, not a list ({_short(value)})"
        if isinstance(value, dict) and isinstance(target, DictConfig):
            found = _container_mismatch(merged, value, f"{name}.")
            if found:
                return found
    return None


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _build(layers: list, interpolated: dict[str, tuple[Any, str]]) -> ExperimentConfig:
    """The dataclasses from ``layers`` (``(source, node)``, merged in order)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

    _require_mandatory(layers)
    merged = OmegaConf.structured(ExperimentConfig)
    for source, node in layers:
        try:
            if "method" in node and node["method"] is not None:
                node = _expand_method(node, merged)
            merged = OmegaConf.merge(merged, node)
        except OmegaConfBaseException as err:
            raise ConfigError(f"{source}: {_merge_message(err, merged, node)}") from err
        except ConfigError as err:
            raise ConfigError(f"{source}: {err}") from err
        except TypeError as err:  # "Cannot merge incompatible container types" (a traceback)
            plain = OmegaConf.to_container(node, resolve=False)
            raise ConfigError(f"{source}: {_container_mismatch(merged, plain) or err}") from err
    _resolve(merged, interpolated)
    # ``method`` is input shorthand: afterwards it names what the settings say.
    fed, cont = merged.federated, merged.continual
    if fed.strategy in STRATEGIES and fed.scope in SCOPES and cont.method in CONTINUAL:
        name = method_name(fed.strategy, fed.scope, cont.method if cont.tasks else None)
        merged = OmegaConf.merge(merged, {"method": name})
    try:
        return OmegaConf.to_object(merged)
    except MissingMandatoryValue as err:
        key = getattr(err, "full_key", "?")
        raise ConfigError(f"{key}: no value; set it, e.g. {key}=/path/to/manners-db") from err
    except OmegaConfBaseException as err:
        raise ConfigError(_omegaconf_message(err)) from err


def _require_mandatory(layers: list) -> None:
    """A ``???`` value (e.g. data.path in conf/data/manners.yaml) must be set by a later
    layer or the command line. (OmegaConf's merge skips ``???``, which would let an earlier
    default - the synthetic data - stand in silently.)"""
    plain = [(source, _plain(node)) for source, node in layers]  # nothing resolved
    for i, (source, values) in enumerate(plain):
        for key in _missing_keys(values):
            later = (_lookup(v, key) for _, v in plain[i + 1 :])
            if not any(v is not None and v != "???" for v in later):
                raise ConfigError(
                    f"{key}: no value (required by {source}); set it, "
                    f"e.g. {key}=/path/to/manners-db"
                )


def _missing_keys(values: dict, prefix: str = "") -> list[str]:
    """Dotted keys whose value is the mandatory marker ``???`` in this layer's values."""
    keys = []
    for key, value in values.items():
        if value == "???":
            keys.append(f"{prefix}{key}")
        elif isinstance(value, dict):
            keys += _missing_keys(value, f"{prefix}{key}.")
    return keys


def _lookup(values: Any, key: str) -> Any:
    """The raw value at dotted ``key`` in a layer's values, None where there is none."""
    for part in key.split("."):
        if not isinstance(values, dict) or part not in values:
            return None
        values = values[part]
    return values


def _plain(node) -> Any:
    """A layer's values as written: dicts and lists, ``${...}`` left unresolved."""
    from omegaconf import OmegaConf

    return OmegaConf.to_container(node, resolve=False)


def _strings(values: Any, key: str = "", keys: bool = False):
    """``(dotted key, string)`` for every string value (and with ``keys``, every key) in
    plain ``values``; list items as ``key[i]``."""
    if isinstance(values, dict):
        for name, value in values.items():
            if keys and isinstance(name, str):
                yield f"{key}.{name}" if key else name, name
            yield from _strings(value, f"{key}.{name}" if key else str(name), keys)
    elif isinstance(values, list | tuple):
        for i, value in enumerate(values):
            yield from _strings(value, f"{key}[{i}]", keys)
    elif isinstance(values, str):
        yield key, values


def _dotlist(overrides) -> Any:
    """The command-line layer; an override whose value YAML cannot read is one line."""
    import yaml
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    # RecursionError: a value nested thousands of levels deep ([[[[...]]]])
    unreadable = (yaml.YAMLError, OmegaConfBaseException, ValueError, RecursionError)
    # before OmegaConf reads them: 'train=5' train.lr_root=0.1 was read, the 5 dropped and
    # nothing said (the ninth fault sweep, c50, c52); the other order, a Merge error
    if clash := _clashing(overrides):
        raise ConfigError(f"command line: {clash}")
    try:
        return OmegaConf.from_dotlist(list(overrides))
    except unreadable as err:
        for override in overrides:  # name the culprit
            try:
                OmegaConf.from_dotlist([override])
            except unreadable as one:
                shown = override if len(override) <= 120 else f"{override[:100]}..."
                raise ConfigError(f"command line: {shown!r}: {_first_line(one)}") from None
        raise ConfigError(f"command line: {_first_line(err)}") from None


def _clashing(overrides) -> str | None:
    """Two overrides that set one setting both whole and by its parts (``data.path=D`` and
    ``data=[1,2]``), which OmegaConf refuses with "Cannot merge incompatible container
    types" or "invalid literal for int()", naming neither (the eighth sweep, a12), or reads
    with one of them dropped: both, named."""
    keys = [override.partition("=")[0] for override in overrides]
    for i, key in enumerate(keys):
        for earlier, other in zip(overrides[:i], keys[:i], strict=True):
            if other.startswith(f"{key}.") or key.startswith(f"{other}."):
                return (
                    f"{earlier!r} and {overrides[i]!r} set {min(key, other, key=len)} both "
                    "whole and by its parts; give one of them"
                )
    return None


def check_interpolations(source: Any, node) -> dict[str, tuple[Any, str]]:
    """``{key: (source, value)}`` for every value holding ``${...}`` in one layer, each
    checked against ``_ALLOWED`` before anything is resolved."""
    import re

    found = {}
    for key, value in _strings(_plain(node)):
        for start in (m.start() for m in re.finditer(r"\$\{", value)):
            escapes = len(value[:start]) - len(value[:start].rstrip("\\"))
            if escapes % 2 == 0 and not re.match(_ALLOWED, value[start:]):
                raise ConfigError(f"{source}: {key}={value!r}: {_POLICY}")
        if "${" in value:
            found[key] = (source, value)
    return found


def _resolve(merged, interpolated: dict[str, tuple[Any, str]]) -> None:
    """Resolve each ``${...}`` once, so that a reference to nothing, a loop, an unset
    variable or a value of the wrong type is one line naming the setting and its layer."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    for key, (source, value) in interpolated.items():
        try:
            OmegaConf.select(merged, key)
        except OmegaConfBaseException as err:
            raise ConfigError(f"{source}: {key}={value!r}: {_first_line(err)}") from None


def _expand_method(node, merged):
    """``method=NAME`` -> strategy and scope; a Table II name sets the CL method too, and,
    if no task schedule is set yet, the schedule of every task in ``data.tasks``; an FL
    name clears the schedule and the CL method."""
    from omegaconf import OmegaConf

    name = str(node["method"])
    if name in METHODS:
        strategy, scope, _ = METHODS[name]
        fl = {"strategy": strategy, "scope": scope}
        return OmegaConf.merge(
            {"federated": fl, "continual": {"tasks": [], "method": "none"}}, node
        )
    if name not in FCL_METHODS:
        known = ", ".join([*METHODS, *FCL_METHODS])
        raise ConfigError(f"method={name}: unknown; known methods: {known}")
    strategy, scope, continual = FCL_METHODS[name]
    update: dict = {
        "federated": {"strategy": strategy, "scope": scope},
        "continual": {"method": continual},
    }
    here = OmegaConf.select(node, "continual.tasks", default=None)
    if not here and not merged.continual.tasks:
        tasks = OmegaConf.select(node, "data.tasks", default=None) or merged.data.tasks
        update["continual"]["tasks"] = [t["name"] for t in tasks]
    # Settings given next to the name (in the same file or command line) win over it.
    return OmegaConf.merge(update, node)


def _merge_message(err: Exception, merged, node) -> str:
    """:func:`_omegaconf_message`, naming the setting and value at fault where OmegaConf's
    message does not (a list item of the wrong type: "Value '$VALUE' of type ..."): each
    setting of ``node`` is merged alone until one fails."""
    from omegaconf import OmegaConf
    from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

    if isinstance(err, ConfigKeyError) and getattr(err, "full_key", None):
        return _unknown_setting(err.full_key, OmegaConf.to_container(node, resolve=False))
    if getattr(err, "full_key", None):
        return _omegaconf_message(err)
    plain = OmegaConf.to_container(node, resolve=False)

    def leaves(value, prefix=""):
        if isinstance(value, dict):
            for key, inner in value.items():
                yield from leaves(inner, f"{prefix}{key}.")
        else:
            yield prefix[:-1], value

    for key, value in leaves(plain):
        single: dict = {}
        *parents, last = key.split(".")
        here = single
        for part in parents:
            here = here.setdefault(part, {})
        here[last] = value
        try:
            OmegaConf.merge(merged, single)
        except OmegaConfBaseException as one:
            return f"{key}={value!r}: {_plain_reason(one, key, merged)}"
    return _omegaconf_message(err)


def _plain_reason(err: Exception, key: str, merged) -> str:
    """OmegaConf's reason a value cannot go at ``key``, in the config's words where its own
    names its internals (the ninth fault sweep, c98-c104, c128, c132: "Merge error: int is
    not a subclass of TrainConfig", "TupleConfig length 1 does not match type hint length
    2")."""
    import re

    from omegaconf import DictConfig, OmegaConf

    text = _first_line(err).replace("Value '$VALUE' of type '$VALUE_TYPE'", "a value")
    here = OmegaConf.select(merged, key, throw_on_missing=False)
    if isinstance(here, DictConfig) and text.startswith("Merge error:"):
        first = next(iter(here), "...")
        return f"a section of settings, not one value; set its parts (e.g. {key}.{first}=...)"
    if found := re.match(r"TupleConfig length (\d+) does not match type hint length (\d+)", text):
        given, wanted = found.groups()
        return f"a list of {wanted} values expected, {given} given"
    return text


def short_setting(name: str) -> str:
    """A setting without its section, for names of trials and cells: ``train.lr_root`` ->
    ``lr_root``, ``continual.lgr.replay`` -> ``lgr.replay`` (a method's setting keeps the
    method's name)."""
    return name.split(".", 1)[-1]


def known_settings() -> list[str]:
    """Every setting's dotted name (``train.lr_top``, ...)."""
    from omegaconf import OmegaConf

    def leaves(values: dict, prefix: str = ""):
        for key, value in values.items():
            if isinstance(value, dict):
                yield from leaves(value, f"{prefix}{key}.")
            else:
                yield f"{prefix}{key}"

    defaults = OmegaConf.structured(ExperimentConfig)
    return list(leaves(OmegaConf.to_container(defaults, resolve=False, throw_on_missing=False)))


def _dotted_key(key: str, written: Any) -> str | None:
    """The key holding a dot, as written in a file's values, on the way to dotted ``key``
    (``tracking.run_name`` for ``{"tracking.run_name": ...}``); None where there is none."""
    parts = key.split(".")
    for i in range(len(parts)):
        if not isinstance(written, dict):
            return None
        for j in range(len(parts), i + 1, -1):  # the longest such key first
            if ".".join(parts[i:j]) in written:
                return ".".join(parts[i:j])
        written = written.get(parts[i])
    return None


def _unknown_setting(key: str, written: dict) -> str:
    """``KEY: unknown setting; did you mean NAME?`` - the closest known settings to what was
    written (the whole dotted name, so ``train.learning_rate`` finds ``train.lr_root``).
    ``key`` is the first unknown part; a section written under it is matched by its
    setting when it holds one (``trian: {lr_top: 1}`` is ``trian.lr_top``)."""
    import difflib

    dotted = _dotted_key(key, written)
    if dotted is not None:  # `tracking.run_name: x` in a file (the sixth fault sweep)
        section, _, rest = dotted.partition(".")
        nest = (
            f"a dotted name is read on the command line only; in a file, nest it: "
            f"`{section}:` and below it, indented, `{rest}: ...`"
        )
        if key in known_settings():
            return f"{key}: {nest}"
        return f"{_unknown_setting(key, {})} ({nest})"
    below = _lookup(written, key)
    if isinstance(below, dict) and len(below) == 1:
        inner, value = next(iter(below.items()))
        if not isinstance(value, dict):
            key = f"{key}.{inner}"
    known = known_settings()
    matcher = difflib.SequenceMatcher(b=key)
    scores = []
    for name in known:
        matcher.set_seq1(name)
        scores.append((matcher.ratio(), name))
    close = [(r, n) for r, n in sorted(scores, reverse=True)[:2] if r >= 0.6]
    close = [n for r, n in close if r >= close[0][0] - 0.05]  # a far second is noise
    hint = f"; did you mean {' or '.join(close)}?" if close else " (--print-config lists them)"
    return f"{key}: unknown setting{hint}"


def _omegaconf_message(err: Exception) -> str:
    key = getattr(err, "full_key", None)
    first = _first_line(err)
    return f"{key}: {first}" if key else first


def _first_line(err: Exception) -> str:
    return str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__


# --------------------------------------------------------------------------- exporting


def to_plain(value: Any) -> Any:
    """Dataclasses -> dicts, tuples -> lists, paths -> strings (YAML/MLflow friendly)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, list | tuple):
        return [to_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: to_plain(v) for k, v in value.items()}
    if isinstance(value, Path):
        return str(value)
    return value


def to_yaml(config: ExperimentConfig) -> str:
    """The resolved config as YAML - what ``--print-config`` shows, the run's
    ``config.yaml`` artifact and what a Flower server sends its robots - with the
    password of ``tracking.uri`` masked (a database URI may hold one; the UI shows the
    artifact to whoever opens the run)."""
    import yaml

    plain = to_plain(config)
    tracking = plain.get("tracking")
    if isinstance(tracking, dict) and tracking.get("uri"):
        tracking["uri"] = mask_password(str(tracking["uri"]))
    return yaml.safe_dump(plain, sort_keys=False)


def flatten(config: ExperimentConfig) -> dict[str, str]:
    """``{"data.clients": "2", ...}``: the resolved config as MLflow params and as a
    checkpoint keeps it, the password of ``tracking.uri`` masked."""
    out: dict[str, str] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}{k}.", v)
        else:
            out[prefix[:-1]] = str(value)

    walk("", to_plain(config))
    if out.get("tracking.uri"):  # what is kept (checkpoints) holds no password
        out["tracking.uri"] = mask_password(out["tracking.uri"])
    return out
