"""Every setting of an experiment, declared once: its type, default, bounds or choices
and a one-line doc, in frozen pydantic dataclasses, one per section of a config. The
loader, the checks, the sweep file's checks, ``--print-config`` and the generated
reference (docs/settings.md) all read these. A method's own settings (``federated.prox``,
``continual.lgr``) are declared beside it in :mod:`fedlgr.core.methods` and added here as
sections from its registry. Rules across settings are each section's ``__post_init__``
and, across sections, :mod:`.rules`."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import field_validator

from fedlgr.core.data.columns import USING_ARROW, USING_CIRCLE
from fedlgr.core.declare import Bool, Float, Int, betas, epoch_count, section, setting
from fedlgr.core.methods import CONTINUAL, SCOPES, STRATEGIES, method_name
from fedlgr.core.settings import rules
from fedlgr.core.settings.rules import (
    MAX_INTERVAL_S,
    MAX_PER_MACHINE,
    MAX_ROUNDS,
    MODULUS,
    PER_MACHINE,
    ROUNDS_BOUND,
    SEED_LIMIT,
)

SEED = f"must be in 0..{SEED_LIMIT - 1} (numpy's and Lightning's seeding take 32-bit seeds)"


def per_machine(default: int | None, doc: str) -> int | None:
    """Processes, torch threads or client threads on one machine: at most MAX_PER_MACHINE."""
    return setting(default, doc, ge=1, le=MAX_PER_MACHINE, over=PER_MACHINE)


def interval(default: float, doc: str, what: str) -> float:
    """Seconds a thread waits between two ``what``: a second (a shorter one writes to the
    store thousands of times a second) to a day."""
    said = (
        f"from 1 to {MAX_INTERVAL_S} seconds (a day: a thread waits this long between two {what})"
    )
    return setting(default, doc, ge=1, le=MAX_INTERVAL_S, said=said)


def default_cache_dir() -> Path:
    """``$FEDLGR_CACHE_DIR``, else ``$XDG_CACHE_HOME/fedlgr``, else ``~/.cache/fedlgr``."""
    if "FEDLGR_CACHE_DIR" in os.environ:
        return Path(os.environ["FEDLGR_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "fedlgr"


# --------------------------------------------------------------------------- data


@section("data.tasks.")
class TaskSpec:
    """A continual-learning task: the scenes whose ``column`` equals ``value``."""

    name: str
    column: str
    value: Float | Int = 1.0  # an integer stays one (the config's hash is of what was written)


DEFAULT_TASKS = (TaskSpec("circle", USING_CIRCLE, 1.0), TaskSpec("arrow", USING_ARROW, 1.0))


@section("data.noise.")
class NoiseConfig:
    """How ``data.augment`` augments the descriptors (``data.modality=features``): each
    training scene becomes ``data.augment_copies`` rows with Gaussian noise on its 27
    descriptors, drawn once (the LEAP-HRI'24 benchmark's augmentation, docs/leap_hri24.md)."""

    std: Float = setting(0.01, "the noise's standard deviation on each descriptor (0..1)", ge=0)
    original: Bool = setting(False, "the first copy is the scene itself, without noise")
    cumulative: Bool = setting(
        False,
        "copy k carries the sum of k draws (std x sqrt(k)), as the LEAP-HRI'24 code's noise "
        "ran; false: every copy its own draw",
    )


Crop = tuple[Int | None, ...]  # four: the rule says what goes where (rules._crop)


@section("data.")
class DataConfig:
    """Where the data is, how it is read, split over clients and into tasks.
    ``partition=dirichlet`` draws each client's share of every group (the scene's task, or
    its mean-label quartile) from Dirichlet(``dirichlet_alpha``)."""

    path: Path = setting(Path("data/manners-synth"), "the dataset folder (all_data.csv, images/)")
    modality: Literal["image", "features"] = setting(
        "image", "what the root reads: the scene's image or its 27 descriptors + 2 mode flags"
    )
    image_size: Int = setting(128, "images are resized to this many pixels a side", ge=16)
    crop: Crop | None = setting(
        None,
        "[left, top, right, bottom] source pixels cut before resizing, null for an image edge "
        "(MANNERS-DB renders: [295, null, 1313, null])",
    )
    on_bad_image: Literal["error", "skip"] = setting(
        "error", "an unreadable image stops the run, or its scene is left out"
    )
    cache: Bool = setting(True, "decode the images once into a store under cache_dir")
    cache_dir: Path = setting(
        doc="the image store's folder ($FEDLGR_CACHE_DIR, else ~/.cache/fedlgr)",
        factory=default_cache_dir,
    )
    test_fraction: Float = setting(
        0.25,
        "the share of scenes in the common test set",
        gt=0,
        lt=1,
        said="must be between 0 and 1",
    )
    clients: Int = setting(2, "how many clients", ge=1, said="need at least 1 client")
    partition: Literal["iid", "dirichlet"] = setting("iid", "how training scenes go to clients")
    dirichlet_alpha: Float = setting(0.5, "partition=dirichlet's concentration", gt=0)
    partition_key: Literal["task", "label"] = setting(
        "task", "dirichlet groups: the scene's task, or its mean-label quartile"
    )
    tasks: tuple[TaskSpec, ...] = setting(
        DEFAULT_TASKS, "the continual-learning tasks: a name, a column and its value"
    )
    augment: Bool = setting(
        False,
        "images: each training scene shown augment_copies times an epoch, flipped and "
        "rotated; descriptors: augment_copies noisy rows per training scene (data.noise)",
    )
    augment_copies: Int = setting(10, "copies of each training scene an epoch", ge=1)
    noise: NoiseConfig = setting(doc="the descriptors' augmentation", factory=NoiseConfig)
    seed: Int = setting(0, "the split's seed", ge=0, lt=SEED_LIMIT, said=SEED)

    def __post_init__(self) -> None:
        rules.data(self)


# --------------------------------------------------------------------------- the model


@section("model.")
class ModelConfig:
    """The scholar: a root (MobileNetV2 features + pool, or an MLP for the features
    modality) and a top (BN -> 32 -> BN -> 8), the paper's Fig. 2."""

    root: Literal["auto", "mobilenet_v2", "mlp"] = setting(
        "auto", "auto: mobilenet_v2 for images, mlp for features"
    )
    weights: str = setting("none", "imagenet | none | path to a state dict file")
    width: Float = setting(1.0, "MobileNetV2's width multiplier (tests use a tiny one)", gt=0)
    mlp_hidden: tuple[Int, ...] = setting((256, 256), "the mlp root's hidden sizes")
    mlp_block: Literal["linear_bn_relu", "linear"] = setting(
        "linear_bn_relu",
        "each hidden size's block (linear: an affine root, the LEAP-HRI'24 model is "
        "mlp_hidden=[16] mlp_block=linear top_hidden=16)",
    )
    mode_flags: Bool = setting(True, "the mlp root reads the 2 mode flags; false: 27 descriptors")
    top_hidden: Int = setting(32, "the top's hidden width", ge=1)
    output_bias: Float | None = setting(
        3.0, "the initial output bias (the Likert scale's middle); null: the Linear's own"
    )
    channels_last: Bool = setting(True, "faster convolutions on CPU and GPU")

    def __post_init__(self) -> None:
        rules.model(self)


@section("train.")
class TrainConfig:
    """Local training of each client, and evaluation."""

    epochs: Int = epoch_count(10, "local epochs per round")
    batch_size: Int = setting(16, "training batch size", ge=1)
    lr_root: Float = setting(1e-3, "the root's Adam learning rate", ge=0)
    lr_top: Float = setting(1e-3, "the top's Adam learning rate", ge=0)
    betas: tuple[Float, Float] = setting((0.9, 0.999), "Adam's two decay rates, each in [0, 1)")
    max_batches: Int | None = setting(None, "cap per epoch (fast dev runs)", ge=1)
    reset_optimizer: Bool = setting(
        False, "a fresh Adam state every round instead of the client's own"
    )
    eval_batch_size: Int = setting(128, "evaluation batch size", ge=1)
    compat_batch_metrics: Bool = setting(
        False,
        "the LEAP-HRI'24 benchmark's biased per-batch scores (docs/leap_hri24.md); for "
        "comparison only",
    )
    weight_decay: Float = setting(
        0.0, "Adam's L2 penalty on every parameter (the LEAP-HRI'24 code's 0.01)", ge=0
    )
    precision: Literal["32-true", "bf16-mixed", "16-mixed"] = setting("32-true", "Fabric's")

    def __post_init__(self) -> None:
        betas("train.betas", self.betas)


# --------------------------------------------------------------------------- federated


@section("federated.faults.")
class FaultsConfig:
    """Faults simulated in one process or Fabric's processes, seeded by the run's seed
    (``fedlgr.core.faults``): clients that drop out of a round, stragglers whose upload comes
    after the round's deadline (dropped), and Byzantine clients whose uploads are altered
    before the server sees them, or who train on poisoned labels."""

    dropout: Float = setting(
        0.0,
        "the probability that a chosen client drops out of a round",
        ge=0,
        lt=1,
        why="the probability that a chosen client drops out of a round",
    )
    straggler: Float = setting(
        0.0,
        "the probability that a client's upload comes after the deadline (dropped)",
        ge=0,
        lt=1,
        why="the probability that a chosen client is late in a round",
    )
    byzantine: Int = setting(
        0,
        "how many clients are Byzantine (drawn once from the seed)",
        ge=0,
        said="must be 0 or more",
    )
    attack: Literal["sign_flip", "noise", "scale", "labels"] = setting(
        "sign_flip", "what the Byzantine clients send"
    )
    noise: Float = setting(
        1.0, "attack=noise: the Gaussian's standard deviation", ge=0, said="must be 0 or more"
    )
    scale: Float = setting(10.0, "attack=scale: the factor on their update")
    label: Float = setting(5.0, "attack=labels: the rating of every action in their scenes")


@section("federated.dp.")
class DPConfig:
    """Client-level differential privacy (DP-FedAvg, :mod:`fedlgr.core.privacy`): each
    client's update clipped to an L2 norm, Gaussian noise on their sum, the accountant's
    epsilon for ``delta`` after every round. Off while ``clip`` is 0."""

    clip: Float = setting(
        0.0, "the L2 norm each update is clipped to (adaptive: the first one); 0: off", ge=0
    )
    noise_multiplier: Float = setting(
        1.0,
        "the noise's standard deviation over the clip norm",
        ge=0,
        le=1000,
        why="beyond it the noise is a thousand times any clipped update, and dp-accounting's "
        "arithmetic fails: epsilon 0.0 at 1e6, an overflow at 1e300",
    )
    delta: Float = setting(
        1e-5, "the delta epsilon is reported for (below 1 / clients)", gt=0, lt=1
    )
    clipping: Literal["fixed", "adaptive"] = setting(
        "fixed", "adaptive: the clip norm moves to a quantile (Andrew et al. 2021)"
    )
    quantile: Float = setting(
        0.5,
        "adaptive: the share of updates the clip norm aims to leave unclipped",
        gt=0,
        lt=1,
        why="the share of updates that adaptive clipping aims to leave unclipped",
    )
    clip_lr: Float = setting(0.2, "adaptive: the clip norm's geometric step", gt=0)
    count_noise: Float = setting(
        0.0,
        "adaptive: the noise on the count of unclipped updates (0: expected clients / 20)",
        ge=0,
    )
    target_epsilon: Float = setting(
        0.0, "over 0: the run stops before a round would exceed it", ge=0
    )

    def __post_init__(self) -> None:
        rules.dp(self)

    @property
    def enabled(self) -> bool:
        return self.clip > 0


def with_methods(registry: dict, family: str):
    """Add one section per registered method with settings (``federated.prox``,
    ``continual.lgr``), each that method's settings: a new method's settings need no edit
    here."""

    def add(cls: type) -> type:
        for m in registry.values():
            if m.settings is not None:
                cls.__annotations__[m.key] = m.settings
                setattr(cls, m.key, setting(doc=f"{m.suffix}'s settings", factory=m.settings))
        return cls

    return add


ServerEval = Literal["off", "on", "auto"]


@section("federated.")
@with_methods(STRATEGIES, "federated")
class FederatedConfig:
    """What is shared (scope), how it is aggregated (strategy, with each strategy's
    settings under ``federated.<strategy>``: ``federated.prox.mu``; docs/methods.md)."""

    strategy: Literal[tuple(STRATEGIES)] = setting("avg", "how uploads are aggregated")
    scope: Literal[tuple(SCOPES)] = setting("full", "what is shared: the whole model, or the root")
    rounds: Int = setting(10, "federated rounds (FL)", ge=1, le=MAX_ROUNDS, over=ROUNDS_BOUND)
    server_eval: ServerEval = setting(
        "off",
        "the server scores the global model on the test scenes every round (on: full scope "
        "only; auto: where the server holds a whole model)",
    )
    fraction: Float = setting(
        1.0,
        "the share of the clients that train in a round (drawn from the seed)",
        gt=0,
        le=1,
        why="the share of the clients that train in a round; 1: all of them",
    )
    evaluate: Literal["all", "chosen", "sample"] = setting(
        "all", "which clients score the global tensors each round (docs/runtimes.md)"
    )
    eval_clients: Int = setting(10, "evaluate=sample: how many clients score", ge=1)
    eval_every: Int = setting(
        1, "clients score every eval_every-th round, each task's last and the run's last", ge=1
    )
    norm_ratio: Float = setting(
        10.0,
        "an update over this many times the median of the round's other updates' norms is "
        "refused (0: no such check)",
    )
    count_cap: Float = setting(
        3.0,
        "a robot whose sample count no roster scenes bound weighs at most this many times the "
        "median of the round's other counts (0: no cap)",
        ge=0,
    )
    faults: FaultsConfig = setting(doc="simulated faults", factory=FaultsConfig)
    dp: DPConfig = setting(doc="client-level differential privacy", factory=DPConfig)

    @field_validator("server_eval", mode="before")
    @classmethod
    def _on_off(cls, value):
        """true/false as YAML or the command line give them: on/off."""
        return {"true": "on", "false": "off"}.get(str(value).lower(), value)

    def __post_init__(self) -> None:
        rules.federated(self)

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


# --------------------------------------------------------------------------- runtime, robots


@section("runtime.")
class RuntimeConfig:
    """Where the clients run: one process by default, or sharded over processes/nodes."""

    accelerator: Literal["auto", "cpu", "gpu", "cuda"] = setting("auto", "auto | cpu | gpu")
    devices: Int = per_machine(1, "processes per node; clients are sharded over all processes")
    num_nodes: Int = setting(1, "machines", ge=1)
    launcher: Literal["ddp", "ddp_spawn"] = setting("ddp", "ddp re-runs the command per process")
    threads: Int | None = per_machine(
        None, "torch threads per process (default: cores / processes)"
    )
    concurrency: Literal["auto", "sequential", "threads", "batched"] = setting(
        "auto",
        "how a process's clients train: one after another, side by side in threads, or "
        "stacked into one model (a GPU); auto: threads on CPU with several clients",
    )
    workers: Int | None = per_machine(
        None, "clients at once with threads (default: min(clients, threads))"
    )
    progress: Bool = setting(True, "progress bars")
    idle_clients: Literal["auto", "live", "memory", "disk"] = setting(
        "auto",
        "where a client not at work keeps its state (docs/runtimes.md, 'Many clients'); "
        "the results are the same whichever holds them",
    )
    idle_memory_mb: Float = setting(
        1024.0,
        "MiB of idle clients' state held in memory before the rest goes to disk",
        ge=0,
        said="must be 0 or more (MiB of idle clients' state held in memory before the "
        "rest goes to disk)",
    )
    timeout_s: Float = setting(
        1800.0,
        "how long a process of a multi-process run waits for the others",
        ge=1,
        le=7 * 86400,
        said="from 1 second to a week (604800)",
    )

    @property
    def world_size(self) -> int:
        return self.devices * self.num_nodes


@section("deploy.secagg.")
class SecAggConfig:
    """Secure aggregation on robots (Flower's SecAgg+, docs/deployment.md): the server
    sees only the sum of the chosen robots' masked, clipped and quantised updates, and
    refuses a sum no honest robots could have sent (over ``norm_bound``)."""

    enabled: Bool = setting(False, "SecAgg+ on")
    clipping_range: Float = setting(1.0, "every value sent is clipped to [-this, this]", gt=0)
    quantization_range: Int = setting(
        4_194_304,
        "levels over [-clipping_range, clipping_range] (2^22)",
        ge=2,
        le=MODULUS // 1024,
        said="must be in [2, 2^22] (1024 robots' quantised values must sum below SecAgg+'s "
        "modulus 2^32)",
    )
    max_samples: Int = setting(
        1000,
        "the most samples a robot weighs: its update travels as n / max_samples x update",
        ge=1,
    )
    norm_bound: Float = setting(
        100.0,
        "each robot clips its update (and payload) to this L2 norm; a sum whose mean update "
        "is over it is refused (under federated.dp: the clip norm instead)",
        gt=0,
    )
    shares: Float = setting(
        1.0,
        "the share of the round's robots each robot's key is split among",
        gt=0,
        le=1,
        why="a share of the round's robots",
    )
    threshold: Float = setting(
        0.5,
        "the share of those shares that rebuilds a key (at least 2)",
        gt=0,
        le=1,
        why="a share of the shares",
    )


@section("deploy.")
class DeployConfig:
    """Real robots behind a Flower SuperLink (``fedlgr deploy``; docs/deployment.md)."""

    min_clients: Int | None = setting(None, "replies a round needs to go on (default: half)", ge=1)
    join_timeout_s: Float = setting(300.0, "how long round 1 waits for the robots to join", gt=0)
    round_timeout_s: Float = setting(600.0, "how long the server waits in one exchange", gt=0)
    evaluate: Literal["with_next_round", "separate"] = setting(
        "with_next_round",
        "a robot scores the new global tensors with the next round's training message, or "
        "in an evaluate exchange every round",
    )
    roster: str | None = setting(
        None,
        "the roster file on the SuperLink's machine: only its robots take part; 'none': any "
        "node (no SuperNode authentication, --insecure test machines only)",
    )
    secagg: SecAggConfig = setting(doc="secure aggregation", factory=SecAggConfig)


@section("tracking.")
class TrackingConfig:
    """MLflow: local sqlite store by default, or a server (``tracking.uri``)."""

    enabled: Bool = setting(True, "log to MLflow")
    uri: str | None = setting(None, "default: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db")
    experiment: str = setting("fedlgr", "the MLflow experiment")
    run_name: str | None = setting(None, "default: the method and setting, e.g. FedAvg-2c-noaug")
    checkpoint: Int = setting(
        1, "a checkpoint every N rounds (and after the last); 0: none", ge=0, why="0: none"
    )
    keep_checkpoints: Int = setting(2, "the newest K are kept while the run goes on", ge=1)
    checkpoint_dir: str | None = setting(
        None, "default: checkpoints/ next to a sqlite store, else ./"
    )
    heartbeat_s: Float = interval(30.0, "a live run's tag fedlgr.heartbeat is never older", "beats")
    system_metrics: Bool = setting(True, "MLflow's system metrics (CPU, memory, GPU)")
    system_metrics_s: Float = interval(10.0, "seconds between two samples of them", "samples")
    detail_metrics: Bool = setting(
        False,
        "per-client and per-action metrics in MLflow too (results.csv always has them)",
    )

    def __post_init__(self) -> None:
        rules.tracking(self)


# --------------------------------------------------------------------------- continual


@section("continual.")
@with_methods(CONTINUAL, "continual")
class ContinualConfig:
    """Federated continual learning (docs/fedlgr.md): a task schedule and a CL method, with
    each method's settings under ``continual.<method>`` (``continual.ewc.lambda_``). With
    tasks, each is trained for ``rounds_per_task`` rounds and ``federated.rounds`` is not
    used; no tasks: plain FL."""

    tasks: tuple[str, ...] = setting((), "task names of data.tasks in training order; []: FL")
    rounds_per_task: Int = setting(5, "rounds per task", ge=1, le=MAX_ROUNDS, over=ROUNDS_BOUND)
    method: Literal[tuple(CONTINUAL)] = setting("none", "the CL method")
    importance_batches: Int | None = setting(
        None, "batches for Fisher / MAS importance (null: all)", ge=1
    )
    freeze_root_bn: Bool = setting(
        False, "root BatchNorm statistics frozen from task 2 (FedLGR: continual.lgr's)"
    )

    def __post_init__(self) -> None:
        rules.continual(self)

    @property
    def settings(self):
        """The method's settings (``continual.<method>``), None where it has none."""
        return getattr(self, CONTINUAL[self.method].section, None)


# --------------------------------------------------------------------------- the experiment


@section("")
class ExperimentConfig:
    """One experiment: every section, and the rules across them (:mod:`.rules`)."""

    method: str | None = setting(None, "a paper name; sets federated.strategy and scope")
    seed: Int = setting(
        0,
        "model initialisation, batch order, augmentation (data.seed: the split)",
        ge=0,
        lt=SEED_LIMIT,
        said=SEED,
    )
    data: DataConfig = setting(doc="the data", factory=DataConfig)
    model: ModelConfig = setting(doc="the scholar", factory=ModelConfig)
    train: TrainConfig = setting(doc="local training", factory=TrainConfig)
    federated: FederatedConfig = setting(doc="aggregation", factory=FederatedConfig)
    runtime: RuntimeConfig = setting(doc="where clients run", factory=RuntimeConfig)
    tracking: TrackingConfig = setting(doc="MLflow", factory=TrackingConfig)
    continual: ContinualConfig = setting(doc="continual learning", factory=ContinualConfig)
    deploy: DeployConfig = setting(doc="robots", factory=DeployConfig)

    def __post_init__(self) -> None:
        rules.experiment(self)

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
