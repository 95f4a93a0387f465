"""Every method fedlgr runs, registered once: the aggregation strategies
(``federated.strategy``) and the continual-learning methods (``continual.method``).

An entry names the method's config value, the part of the paper's method name it gives
(``Prox``: FedProx, FedRootProx; ``EWC``: FedAvg-EWC, FedRoot-EWC), its class by dotted
path (imported when a run builds it, so this module and the config stay torch-free) and
the dataclass of its settings, which live under ``federated.<key>.*`` or
``continual.<key>.*`` (``federated.prox.mu``, ``continual.lgr.hidden``). The config's
sections, the paper's method names (``method=FedRoot-SI``), the reports' rows and the
tests' method lists are all read from here: adding a method is its module, its entry here
and a conf yaml (docs/development.md, "Adding a method").
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass, field
from typing import Any

from fedlgr.errors import ConfigError


class Settings:
    """Base of a method's settings (a frozen dataclass). Each field declares the values it
    takes (:func:`setting`); the config checks them where it is loaded, naming each by its
    full setting (``continual.lgr.hidden``)."""


@dataclass(frozen=True)
class Bounds:
    """The values a method's setting takes: ``least <= value <= most``, ``above < value <
    below`` (each bound optional), one of ``choices``, or a ``kind`` with its own rule
    (``epochs``: a count of epochs; ``betas``: Adam's two decay rates)."""

    least: float | None = None
    most: float | None = None
    above: float | None = None
    below: float | None = None
    choices: tuple[str, ...] = ()
    kind: str = ""
    reason: str = ""  # said after the bound when a value breaks it


def setting(default: Any, **bounds: Any) -> Any:
    """A settings field with its default and its :class:`Bounds`."""
    return field(default=default, metadata={"bounds": Bounds(**bounds)})


def declared(**fields: Any) -> type[Settings]:
    """A method's settings declared in its registry entry: a frozen dataclass of
    ``fields``, each made with :func:`setting` (``declared(lr=setting(1.0, above=0))``),
    named after the method when it is registered."""
    spec = [(name, type(f.default), f) for name, f in fields.items()]
    return dataclasses.make_dataclass("Settings", spec, bases=(Settings,), frozen=True)


def bounds(field_: Any) -> Bounds:
    """The bounds a settings field declares (none: any value of its type)."""
    return field_.metadata.get("bounds", Bounds())


@dataclass(frozen=True)
class Method:
    """One registered method."""

    key: str  # its config value: federated.strategy=prox, continual.method=ewc
    suffix: str  # its part of the paper's name: Prox, EWC
    target: str | None  # "module:Class", imported by load(); None: no class (continual none)
    paper: str = ""  # the publication it follows
    settings: type[Settings] | None = None  # under federated.<key> / continual.<key>
    uses: str | None = None  # another method's settings section (EWC-Online uses ewc's)
    scopes: tuple[str, ...] = ("full", "root")  # the aggregation scopes it works with
    # (strategy, scope) -> its name where it is not the scope's prefix + suffix (FedLGR)
    names: dict[tuple[str, str], str] = field(default_factory=dict)
    in_paper: bool = True  # a row of the paper's tables (else a report shows it where it ran)

    def load(self) -> Any:
        """The method's class (imports its module: torch)."""
        if self.target is None:
            raise ConfigError(f"{self.key}: a method without a class")
        module, _, name = self.target.partition(":")
        return getattr(importlib.import_module(module), name)

    @property
    def section(self) -> str:
        """The settings section it reads (its own, or the one it ``uses``)."""
        return self.uses or self.key


def _register(family: str, *methods: Method) -> dict[str, Method]:
    table = {}
    for m in methods:
        if m.key in table:
            raise ValueError(f"{family}.{m.key} registered twice")
        if m.settings is not None and m.settings.__name__ == "Settings":  # declared()
            m.settings.__name__ = m.settings.__qualname__ = f"{m.suffix}Settings"
        table[m.key] = m
    return table


# --------------------------------------------------------------------------- strategies


@dataclass(frozen=True)
class ProxSettings(Settings):
    mu: float = setting(0.01, least=0)  # client loss + mu/2 ||w - w_global||^2


@dataclass(frozen=True)
class OptSettings(Settings):
    """FedOpt's server optimiser (Reddi et al. 2021, Algorithm 2): x <- x + lr m / (sqrt(v)
    + tau), v by the variant (FedAdam, FedYogi, FedAdagrad; adagrad reads betas[0] only)."""

    lr: float = setting(0.01, above=0)
    betas: tuple[float, float] = setting((0.9, 0.99), kind="betas")
    tau: float = setting(1e-3, above=0)
    variant: str = setting("adam", choices=("adam", "yogi", "adagrad"))
    # the second moment's start: tau2 (the paper's v_-1 = tau^2) | zero (fedlgr's earlier form)
    v0: str = setting("tau2", choices=("tau2", "zero"))


@dataclass(frozen=True)
class DistillSettings(Settings):
    weight: float = setting(0.5, least=0, most=1)  # weight of the teacher term in the student loss


@dataclass(frozen=True)
class AvgMSettings(Settings):
    """Server momentum on the mean update: v <- momentum v + Delta; x <- x + lr v. The
    default keeps Hsu et al.'s effective learning rate lr / (1 - momentum) at 1: lr 1 with
    momentum 0.9 diverged on the demo (docs/methods.md)."""

    momentum: float = setting(0.9, least=0, below=1)
    lr: float = setting(0.1, above=0)


STRATEGY = "fedlgr.core.strategies"
STRATEGIES = _register(
    "federated",
    Method("avg", "Avg", f"{STRATEGY}.base:FedAvg", "McMahan et al. 2017"),
    Method("bn", "BN", f"{STRATEGY}.fedbn:FedBN", "Li et al. 2021"),
    Method("prox", "Prox", f"{STRATEGY}.fedprox:FedProx", "Li et al. 2020", ProxSettings),
    Method("opt", "Opt", f"{STRATEGY}.fedopt:FedOpt", "Reddi et al. 2021", OptSettings),
    Method("distill", "Distill", f"{STRATEGY}.feddistill:FedDistill", "", DistillSettings),
    Method(
        "avgm",
        "AvgM",
        f"{STRATEGY}.fedavgm:FedAvgM",
        "Hsu et al. 2019",
        AvgMSettings,
        in_paper=False,
    ),
    Method(
        "scaffold",
        "SCAFFOLD",
        f"{STRATEGY}.scaffold:Scaffold",
        "Karimireddy et al. 2020",
        declared(lr=setting(1.0, above=0)),  # the global learning rate
        names={("scaffold", "full"): "SCAFFOLD"},
        in_paper=False,
    ),
    Method("median", "Median", f"{STRATEGY}.median:FedMedian", "Yin et al. 2018", in_paper=False),
    Method(
        "trimmed",
        "TrimmedAvg",
        f"{STRATEGY}.trimmed:FedTrimmedAvg",
        "Yin et al. 2018",
        declared(beta=setting(0.2, least=0, below=0.5)),  # the fraction cut at either end
        in_paper=False,
    ),
    Method(
        "krum",
        "Krum",
        f"{STRATEGY}.krum:Krum",
        "Blanchard et al. 2017",
        declared(f=setting(1, least=0), m=setting(1, least=1)),  # Byzantine clients; kept
        names={("krum", "full"): "Krum"},
        in_paper=False,
    ),
)


# --------------------------------------------------------------------------- continual


@dataclass(frozen=True)
class EWCSettings(Settings):
    """EWC and EWC-Online: lambda_ / 2 * sum F (theta - theta*)^2. The default lambda is
    sweeps/ewc.yaml's best on the synthetic descriptors (docs/fedlgr.md, "EWC's lambda")."""

    lambda_: float = setting(1000.0, least=0)
    # the Fisher, each scene's squared gradient averaged over the task's scenes: empirical
    # (of its MSE to the labels, Kirkpatrick et al.'s) | model (to outputs + N(0, 4) noise) |
    # batch (each mini-batch's squared gradient, and no 1/2 in the penalty: fedlgr's earlier
    # form, about 1/batch-size of the others) | batch_model (model so: fedlgr's earlier form)
    fisher: str = setting("empirical", choices=("empirical", "model", "batch", "batch_model"))
    gamma: float = setting(0.9, least=0, most=1)  # EWC-Online: decay of the running Fisher


@dataclass(frozen=True)
class SISettings(Settings):
    c: float = setting(1.0, least=0)  # penalty coefficient
    xi: float = setting(0.1, least=0)  # damping
    # none (Zenke et al.'s eq. 5) | task (each task's gain clamped at 0: fedlgr's
    # earlier form) | total (the summed importance clamped at 0: the authors' code)
    clamp: str = setting("none", choices=("none", "task", "total"))
    # the gradient in the path integral: loss (without SI's penalty, as published) |
    # loss+penalty (fedlgr's earlier form)
    path_gradient: str = setting("loss", choices=("loss", "loss+penalty"))


@dataclass(frozen=True)
class MASSettings(Settings):
    lambda_: float = setting(1.0, least=0)  # penalty coefficient
    # sample (|gradient of each scene's squared output norm|, averaged: Aljundi et al.'s) |
    # batch (of each mini-batch's mean: fedlgr's earlier form)
    importance: str = setting("sample", choices=("sample", "batch"))


@dataclass(frozen=True)
class NRSettings(Settings):
    memory: int = setting(100, least=0)  # scenes kept per client (all past tasks together)
    replay_ratio: float = setting(0.5, least=0)  # memory samples per current sample in a batch


@dataclass(frozen=True)
class LwFSettings(Settings):
    """LwF for regression: loss + alpha * mean (f(x) - f_start(x))^2 from the second task."""

    alpha: float = setting(1.0, least=0)


@dataclass(frozen=True)
class LGRSettings(Settings):
    """FedLGR's latent generative replay (docs/fedlgr.md). ``replay_layer=freeze`` has a
    rule across settings, checked with the config: it needs ``train_blocks`` >= 1,
    ``schedule=joint`` and no compensation."""

    # two_phase (top, then root) | joint (one pass)
    schedule: str = setting("two_phase", choices=("two_phase", "joint"))
    # generator | stored (the oracle: real past latents kept)
    replay: str = setting("generator", choices=("generator", "stored"))
    freeze_root_bn: bool = True  # root BatchNorm statistics frozen from task 2
    hidden: int = setting(512, least=1)  # the VAE's hidden width
    latent: int = setting(16, least=1)  # the VAE's latent size
    epochs: int = setting(300, kind="epochs")  # the VAE's most epochs at the end of each task
    # ... stop after this many epochs without held-out gain (0: never)
    patience: int = setting(20, least=0)
    # ... share of a task's latents held out (none under 10 latents)
    holdout: float = setting(0.2, least=0, below=1)
    batch_size: int = setting(32, least=1)
    lr: float = setting(1e-3, least=0)  # the generator's learning rate
    beta: float = setting(4.0, least=0)  # weight of the VAE's KL term
    # VAE codes from a Gaussian fitted to the training codes | prior
    sampler: str = setting("posterior", choices=("posterior", "prior"))
    lr_root: float = setting(1e-5, least=0)  # the root's learning rate from task 2 on (lr_R)
    # two_phase: root epochs per round (None: train.epochs)
    root_epochs: int | None = setting(1, least=0, kind="epochs")
    replay_ratio: float = setting(4.0, least=0)  # pseudo-samples per real sample for the top
    # Keeping replayed latents valid while the root learns (docs/fedlgr.md): none |
    # compensate | distill | compensate+distill. The defaults (distill at weight 10, the
    # last root block trained) are sweeps/fedlgr_drift_image.yaml's and
    # sweeps/fedlgr_distill_image.yaml's best point; none + train_blocks null is the paper's.
    drift: str = setting("distill", choices=("none", "compensate", "distill", "compensate+distill"))
    # compensate: ridge of the drift map (x mean eigenvalue)
    compensate_ridge: float = setting(
        1.0,
        above=0,
        reason="the drift map is fitted on a client's scenes, fewer than the root's features",
    )
    distill_weight: float = setting(10.0, least=0)  # distill: weight of the latent distillation
    # from task 2 only the root's last k blocks train (null: all)
    train_blocks: int | None = setting(1, least=0)
    # latent (the root's output) | freeze (the k blocks' input)
    replay_layer: str = setting("latent", choices=("latent", "freeze"))


CL = "fedlgr.core.continual"
CONTINUAL = _register(
    "continual",
    Method("none", "FT", None, "fine-tuning: the tasks in sequence, nothing kept"),
    Method("ewc", "EWC", f"{CL}.ewc:EWC", "Kirkpatrick et al. 2017", EWCSettings),
    Method("ewc_online", "EWCOnline", f"{CL}.ewc:EWCOnline", "Schwarz et al. 2018", uses="ewc"),
    Method("si", "SI", f"{CL}.si:SI", "Zenke et al. 2017", SISettings),
    Method("mas", "MAS", f"{CL}.mas:MAS", "Aljundi et al. 2018", MASSettings),
    Method("nr", "NR", f"{CL}.rehearsal:NaiveRehearsal", "Hsu et al. 2018", NRSettings),
    Method("lwf", "LwF", f"{CL}.lwf:LwF", "Li & Hoiem 2016", LwFSettings, in_paper=False),
    Method(
        "lgr",
        "LGR",
        f"{CL}.lgr:LatentReplay",
        "Churamani et al. (FedLGR)",
        LGRSettings,
        scopes=("root",),
        names={("avg", "root"): "FedLGR"},
    ),
)

SCOPES = {"full": "Fed", "root": "FedRoot"}


def method_name(strategy: str, scope: str, continual: str | None = None) -> str:
    """The paper's name: ``("avg", "full")`` -> ``FedAvg``, ``("bn", "root")`` ->
    ``FedRootBN``; with a task schedule, Table II's ``FedAvg-EWC``, ``FedRoot-NR``,
    ``FedLGR`` (FedRoot + latent generative replay), and ``FedRoot-FT`` for training on the
    tasks in sequence with no continual-learning method (the forgetting baseline)."""
    strategy_ = STRATEGIES[strategy]
    base = strategy_.names.get((strategy, scope), SCOPES[scope] + strategy_.suffix)
    if continual is None:
        return base
    cl = CONTINUAL[continual]
    if (strategy, scope) in cl.names:
        return cl.names[(strategy, scope)]
    return f"{'FedRoot' if base == 'FedRootAvg' else base}-{cl.suffix}"


# Paper name -> (strategy, scope, continual method or None for FL). The FCL benchmark
# (Table II) pairs every CL method with FedAvg aggregation, full or root scope.
METHODS = {method_name(st, sc): (st, sc, None) for sc in SCOPES for st in STRATEGIES}
FCL_METHODS = {
    method_name("avg", sc, cl): ("avg", sc, cl)
    for sc in SCOPES
    for cl, m in CONTINUAL.items()
    if sc in m.scopes
}


def plugin_metrics(strategy: str, continual: str) -> list[str]:
    """What a method's client plugins measure, ``<plugin>/<name>``: its strategy's (the
    classes ``client_plugin_types`` names) and its continual-learning method's. Imports
    their modules (torch)."""
    types = list(STRATEGIES[strategy].load().client_plugin_types)
    cl = CONTINUAL[continual]
    types += [] if cl.target is None else [cl.load()]
    return [f"{p.name}/{m}" for p in types for m in p.metric_names]


def in_paper(name: str) -> bool:
    """Is the method (a paper name, ``FedRoot-SI``) one of the paper's, made of a strategy
    and a CL method it compares?"""
    strategy, _, continual = {**METHODS, **FCL_METHODS}[name]
    return STRATEGIES[strategy].in_paper and (continual is None or CONTINUAL[continual].in_paper)
