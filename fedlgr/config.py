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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fedlgr.data.config import DataConfig
from fedlgr.errors import ConfigError

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
STRATEGIES = {"avg": "Avg", "bn": "BN", "prox": "Prox", "opt": "Opt", "distill": "Distill"}
SCOPES = {"full": "Fed", "root": "FedRoot"}
ROOTS = ("auto", "mobilenet_v2", "mlp")
PRECISIONS = ("32-true", "bf16-mixed", "16-mixed")


def method_name(strategy: str, scope: str) -> str:
    """The paper's name: ``("avg", "full")`` -> ``FedAvg``, ``("bn", "root")`` -> ``FedRootBN``."""
    return SCOPES[scope] + STRATEGIES[strategy]


METHODS = {method_name(st, sc): (st, sc) for sc in SCOPES for st in STRATEGIES}


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
        _positive("train.epochs", self.epochs)
        _positive("train.batch_size", self.batch_size)
        _positive("train.eval_batch_size", self.eval_batch_size)
        if self.max_batches is not None:
            _positive("train.max_batches", self.max_batches)
        for name in ("lr_root", "lr_top"):
            if getattr(self, name) < 0:
                raise ConfigError(f"train.{name}={getattr(self, name)}: must be >= 0")
        _choice("train.precision", self.precision, PRECISIONS)


@dataclass(frozen=True)
class FederatedConfig:
    """What is shared (scope), how it is aggregated (strategy), and the strategies'
    settings (SPEC 4.1)."""

    strategy: str = "avg"
    scope: str = "full"
    rounds: int = 10
    prox_mu: float = 0.01  # FedProx: client loss + mu/2 ||w - w_global||^2
    server_lr: float = 0.01  # FedOpt (FedAdam, Reddi et al. 2021): eta
    server_betas: tuple[float, float] = (0.9, 0.99)
    server_tau: float = 1e-3
    distill_weight: float = 0.5  # FedDistill: weight of the teacher term in the student loss

    def __post_init__(self) -> None:
        _choice("federated.strategy", self.strategy, tuple(STRATEGIES))
        _choice("federated.scope", self.scope, tuple(SCOPES))
        _positive("federated.rounds", self.rounds)
        if self.prox_mu < 0:
            raise ConfigError(f"federated.prox_mu={self.prox_mu}: must be >= 0")
        if not 0.0 <= self.distill_weight <= 1.0:
            raise ConfigError(f"federated.distill_weight={self.distill_weight}: must be in 0..1")
        if self.server_tau <= 0 or self.server_lr <= 0:
            raise ConfigError("federated.server_lr and federated.server_tau must be > 0")

    @property
    def method(self) -> str:
        return method_name(self.strategy, self.scope)


@dataclass(frozen=True)
class RuntimeConfig:
    """Where the clients run: one process by default, or sharded over processes/nodes."""

    accelerator: str = "auto"  # auto | cpu | gpu
    devices: int = 1  # processes per node; clients are sharded over all processes
    num_nodes: int = 1
    launcher: str = "ddp"  # ddp (re-runs the command per process) | ddp_spawn
    threads: int | None = None  # torch threads per process (default: cores / processes)
    progress: bool = True

    def __post_init__(self) -> None:
        _choice("runtime.accelerator", self.accelerator, ("auto", "cpu", "gpu", "cuda"))
        _choice("runtime.launcher", self.launcher, ("ddp", "ddp_spawn"))
        _positive("runtime.devices", self.devices)
        _positive("runtime.num_nodes", self.num_nodes)
        if self.threads is not None:
            _positive("runtime.threads", self.threads)

    @property
    def world_size(self) -> int:
        return self.devices * self.num_nodes


@dataclass(frozen=True)
class TrackingConfig:
    """MLflow: local sqlite store by default, or a server (``tracking.uri``)."""

    enabled: bool = True
    uri: str | None = None  # default: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db
    experiment: str = "fedlgr"
    run_name: str | None = None  # default: the method and setting, e.g. FedAvg-2c-noaug

    def __post_init__(self) -> None:
        if not self.experiment:
            raise ConfigError("tracking.experiment: must not be empty")


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

    def __post_init__(self) -> None:
        if self.method is not None and self.method != self.federated.method:
            raise ConfigError(f"method={self.method} disagrees with federated.strategy/scope")
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
        if self.data.modality == "image" and root == "mlp":
            raise ConfigError("model.root=mlp reads the descriptors: set data.modality=features")

    @property
    def root_kind(self) -> str:
        if self.model.root != "auto":
            return self.model.root
        return "mlp" if self.data.modality == "features" else "mobilenet_v2"

    @property
    def method_name(self) -> str:
        return self.federated.method

    @property
    def run_name(self) -> str:
        if self.tracking.run_name:
            return self.tracking.run_name
        aug = "aug" if self.data.augment else "noaug"
        return f"{self.method_name}-{self.data.clients}c-{aug}"


def _choice(setting: str, value: str, options: tuple[str, ...]) -> None:
    if value not in options:
        raise ConfigError(f"{setting}={value!r}: must be one of {', '.join(options)}")


def _positive(setting: str, value: int) -> None:
    if value < 1:
        raise ConfigError(f"{setting}={value}: must be >= 1")


# --------------------------------------------------------------------------- loading


def _read_layers(path: Path, seen: tuple[Path, ...] = ()) -> list[Any]:
    """The YAML at ``path`` preceded by what it includes, each as an OmegaConf node."""
    from omegaconf import OmegaConf

    path = path.resolve()
    if path in seen:
        raise ConfigError(f"{path}: includes itself (via {' -> '.join(p.name for p in seen)})")
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        node = OmegaConf.load(path)
    except Exception as err:
        raise ConfigError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from err
    if node is None or not OmegaConf.is_dict(node):
        raise ConfigError(f"{path}: expected a mapping of settings at the top level")
    includes = node.pop("includes", [])
    if isinstance(includes, str) or not OmegaConf.is_list(includes):
        includes = [includes] if isinstance(includes, str) else list(includes or [])
    layers: list[Any] = []
    for inc in includes:
        target = Path(str(inc)).with_suffix(".yaml")
        if not target.is_absolute():  # relative to conf/, else to the including file
            target = CONF_DIR / target if (CONF_DIR / target).is_file() else path.parent / target
        layers += _read_layers(target, (*seen, path))
    return [*layers, (path, node)]


def load_config(
    path: Path | str | None = None, overrides: list[str] | tuple[str, ...] = ()
) -> ExperimentConfig:
    """Merge the defaults, ``path`` (with its includes) and ``overrides`` (``key=value``)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

    layers = _read_layers(Path(path)) if path is not None else []
    bad = [o for o in overrides if "=" not in o or o.startswith("=")]
    if bad:
        raise ConfigError(f"override {bad[0]!r}: expected key=value (e.g. federated.rounds=5)")
    layers = [*layers, ("command line", OmegaConf.from_dotlist(list(overrides)))]
    _require_mandatory(layers)
    merged = OmegaConf.structured(ExperimentConfig)
    for source, node in layers:
        try:
            if "method" in node and node["method"] is not None:
                node = _expand_method(node)
            merged = OmegaConf.merge(merged, node)
        except OmegaConfBaseException as err:
            raise ConfigError(f"{source}: {_omegaconf_message(err)}") from err
        except ConfigError as err:
            raise ConfigError(f"{source}: {err}") from err
    # ``method`` is input shorthand: afterwards it names what the settings say.
    fed = merged.federated
    if fed.strategy in STRATEGIES and fed.scope in SCOPES:
        merged = OmegaConf.merge(merged, {"method": method_name(fed.strategy, fed.scope)})
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
    from omegaconf import OmegaConf

    for i, (source, node) in enumerate(layers):
        for key in _missing_keys(node):
            later = (OmegaConf.select(n, key, default=None) for _, n in layers[i + 1 :])
            if not any(v is not None and v != "???" for v in later):
                raise ConfigError(
                    f"{key}: no value (required by {source}); set it, "
                    f"e.g. {key}=/path/to/manners-db"
                )


def _missing_keys(node, prefix: str = "") -> list[str]:
    """Dotted keys whose value is the mandatory marker ``???`` in this layer."""
    from omegaconf import OmegaConf

    keys = []
    for key in node:
        if OmegaConf.is_missing(node, key):
            keys.append(f"{prefix}{key}")
        elif OmegaConf.is_dict(node[key]):
            keys += _missing_keys(node[key], f"{prefix}{key}.")
    return keys


def _expand_method(node):
    from omegaconf import OmegaConf

    name = str(node["method"])
    if name not in METHODS:
        raise ConfigError(f"method={name}: unknown; known methods: {', '.join(METHODS)}")
    strategy, scope = METHODS[name]
    return OmegaConf.merge(node, {"federated": {"strategy": strategy, "scope": scope}})


def _omegaconf_message(err: Exception) -> str:
    key = getattr(err, "full_key", None)
    first = str(err).splitlines()[0] if str(err) else type(err).__name__
    return f"{key}: {first}" if key else first


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
    import yaml

    return yaml.safe_dump(to_plain(config), sort_keys=False)


def flatten(config: ExperimentConfig) -> dict[str, str]:
    """``{"data.clients": "2", ...}``: the resolved config as MLflow params."""
    out: dict[str, str] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}{k}.", v)
        else:
            out[prefix[:-1]] = str(value)

    walk("", to_plain(config))
    return out
