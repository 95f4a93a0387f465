"""The experiment's settings: typed dataclasses, one per section of a config, the single
source of truth for every setting and its default. Each checks itself on construction
(``__post_init__`` calls its rules in :mod:`fedlgr.shell.checks.settings`, the rules across
sections in :mod:`fedlgr.shell.checks.experiment`), so a config loaded from YAML and one
built in code are refused alike, in one line naming the setting.
A method's own settings (``federated.prox``, ``continual.lgr``) are dataclasses next to the
method in :mod:`fedlgr.core.methods`, added here as sections from its registry."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from fedlgr.core.methods import CONTINUAL, STRATEGIES, method_name
from fedlgr.shell.checks.experiment import check_experiment
from fedlgr.shell.checks.settings import (
    check_continual,
    check_deploy,
    check_dp,
    check_faults,
    check_federated,
    check_model,
    check_runtime,
    check_secagg,
    check_tracking,
    check_train,
)
from fedlgr.shell.config.data import DataConfig

SERVER_EVAL_ALIASES = {"true": "on", "false": "off"}


@dataclass(frozen=True)
class ModelConfig:
    """The scholar: a root (MobileNetV2 features + pool, or an MLP for the features
    modality) and a top (BN -> 32 -> BN -> 8), the paper's Fig. 2."""

    root: str = "auto"  # auto: mobilenet_v2 for images, mlp for features
    weights: str = "none"  # imagenet | none | path to a state dict file
    width: float = 1.0  # MobileNetV2 width multiplier (tests use a tiny one)
    mlp_hidden: tuple[int, ...] = (256, 256)
    # each hidden size's block: linear_bn_relu, or linear (an affine root: the LEAP-HRI'24
    # model is model.mlp_hidden=[16] model.mlp_block=linear model.top_hidden=16)
    mlp_block: str = "linear_bn_relu"
    mode_flags: bool = True  # the mlp root reads the 2 mode flags; false: the 27 descriptors only
    top_hidden: int = 32
    # initial output bias: the middle of the Likert scale; null: the Linear layer's own init
    output_bias: float | None = 3.0
    channels_last: bool = True  # faster convolutions on CPU and GPU

    def __post_init__(self) -> None:
        check_model(self)


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
    # The LEAP-HRI'24 benchmark's scores (Checker et al. 2024, its FCL code's test()): test
    # batches of 16 (drop_last) in its order, the RMSE of each flattened batch and each
    # action's PCC, averaged over batches (biased: docs/leap_hri24.md). For comparison only.
    compat_batch_metrics: bool = False
    # Adam's L2 penalty (torch.optim.Adam's weight_decay, added to the gradient, not AdamW's
    # decoupled decay), on every parameter: the LEAP-HRI'24 code's 0.01; 0: none.
    weight_decay: float = 0.0
    precision: str = "32-true"

    def __post_init__(self) -> None:
        check_train(self)


def _with_sections(base: type, registry: dict) -> type:
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


@dataclass(frozen=True)
class FaultsConfig:
    """Faults simulated in one process or Fabric's processes, seeded by the run's seed
    (``fedlgr.core.faults``): clients that drop out of a round, stragglers whose upload comes
    after the round's deadline (dropped), and Byzantine clients whose uploads are altered
    before the server sees them, or who train on poisoned labels."""

    dropout: float = 0.0  # the probability that a chosen client drops out of a round
    # the probability that a client that trains sends its upload after the round's deadline
    # (it is dropped, never used stale)
    straggler: float = 0.0
    byzantine: int = 0  # how many clients are Byzantine (drawn once from the seed)
    attack: str = "sign_flip"  # what they send: sign_flip | noise | scale | labels
    noise: float = 1.0  # attack=noise: the Gaussian's standard deviation, on every value
    scale: float = 10.0  # attack=scale: the factor on their update
    label: float = 5.0  # attack=labels: the rating of every action in their training scenes

    def __post_init__(self) -> None:
        check_faults(self)


@dataclass(frozen=True)
class DPConfig:
    """Client-level differential privacy (DP-FedAvg, :mod:`fedlgr.core.privacy`): each
    client's update clipped to an L2 norm, Gaussian noise on their sum, the accountant's
    epsilon for ``delta`` after every round. Off while ``clip`` is 0."""

    clip: float = 0.0  # the L2 norm each update is clipped to (adaptive: the first one); 0: off
    noise_multiplier: float = 1.0  # the noise's standard deviation over the clip norm
    delta: float = 1e-5  # the delta epsilon is reported for (below 1 / clients)
    clipping: str = "fixed"  # fixed | adaptive (Andrew et al. 2021: clip moves to a quantile)
    quantile: float = 0.5  # adaptive: the share of updates the clip norm aims to leave unclipped
    clip_lr: float = 0.2  # adaptive: the clip norm's geometric step
    # adaptive: the noise on the count of unclipped updates (0: the expected clients / 20)
    count_noise: float = 0.0
    target_epsilon: float = 0.0  # over 0: the run stops before a round would exceed it

    def __post_init__(self) -> None:
        check_dp(self)

    @property
    def enabled(self) -> bool:
        return self.clip > 0


@dataclass(frozen=True)
class _FederatedConfig:
    """What is shared (scope), how it is aggregated (strategy, with each strategy's
    settings under ``federated.<strategy>``: ``federated.prox.mu``; docs/methods.md)."""

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
    # Which clients score the global tensors each round (docs/runtimes.md, "Many
    # clients"): all (the paper's protocol), chosen (the round's participants), sample (a
    # fixed subset of eval_clients clients drawn once from the seed). The round's test
    # scores are the mean over the clients evaluated.
    evaluate: str = "all"
    eval_clients: int = 10
    # Clients score every eval_every-th round, each task's last one and the run's last
    # one; no client scores the others (no test/* figures for them). 1: every round.
    eval_every: int = 1
    # An upload whose update (its tensors minus the global ones) has a norm over this many
    # times the median of the round's other updates is refused (0: no such check). Every upload's
    # keys, shapes, dtypes, values and sample count are checked whatever this says.
    norm_ratio: float = 10.0
    faults: FaultsConfig = field(default_factory=FaultsConfig)
    dp: DPConfig = field(default_factory=DPConfig)

    def __post_init__(self) -> None:
        # true/false as YAML or the command line give them: on/off
        value = SERVER_EVAL_ALIASES.get(str(self.server_eval).lower(), self.server_eval)
        object.__setattr__(self, "server_eval", value)
        check_federated(self)

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


FederatedConfig = _with_sections(_FederatedConfig, STRATEGIES)


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
    # Where a client not at work in a round keeps its state (docs/runtimes.md, "Many
    # clients"): live (whole, as a model, optimiser and plugins), memory (compact: only
    # what differs from the global tensors, its optimiser, plugins' and generators' state),
    # disk (compact, in files under the checkpoint folder); auto: live up to 32 clients
    # per process, else compact in memory up to idle_memory_mb, the rest on disk. The
    # results are the same whichever holds them.
    idle_clients: str = "auto"
    idle_memory_mb: float = 1024.0
    # How long a process of a multi-process run waits for the others: for all of them to
    # join at the start (a node never started), and at each exchange of a round (torch's
    # default, 30 min, lets a slow process's clients finish their round).
    timeout_s: float = 1800.0

    def __post_init__(self) -> None:
        check_runtime(self)

    @property
    def world_size(self) -> int:
        return self.devices * self.num_nodes


@dataclass(frozen=True)
class SecAggConfig:
    """Secure aggregation on robots (Flower's SecAgg+, docs/deployment.md): the server
    sees only the sum of the chosen robots' masked, clipped and quantised updates."""

    enabled: bool = False
    clipping_range: float = 1.0  # every value sent is clipped to [-this, this]
    quantization_range: int = 4_194_304  # 2^22 levels over [-clipping_range, clipping_range]
    # the most training samples a robot weighs: its update travels as n / max_samples x update
    max_samples: int = 1000
    shares: float = 1.0  # the share of the round's robots each robot's key is split among
    threshold: float = 0.5  # the share of those shares that rebuilds a key (at least 2)

    def __post_init__(self) -> None:
        check_secagg(self)


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
    secagg: SecAggConfig = field(default_factory=SecAggConfig)

    def __post_init__(self) -> None:
        check_deploy(self)


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
        check_tracking(self)


@dataclass(frozen=True)
class _ContinualConfig:
    """Federated continual learning (docs/fedlgr.md): a task schedule and a CL method, with
    each method's settings under ``continual.<method>`` (``continual.ewc.lambda_``).

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
        check_continual(self)

    @property
    def settings(self):
        """The method's settings (``continual.<method>``), None where it has none."""
        return getattr(self, CONTINUAL[self.method].section, None)


ContinualConfig = _with_sections(_ContinualConfig, CONTINUAL)


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
        check_experiment(self)

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
