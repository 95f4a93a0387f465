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

import importlib
from dataclasses import dataclass, field
from typing import Any, ClassVar

from fedlgr.errors import ConfigError
from fedlgr.shell.data.config import betas as check_betas
from fedlgr.shell.data.config import check_numbers, choice, nonnegative, positive
from fedlgr.shell.data.config import epochs as check_epochs


class Settings:
    """Base of a method's settings (a frozen dataclass): checks its own values, naming
    each by its full setting (``section`` is set when the method is registered)."""

    section: ClassVar[str] = ""

    def __post_init__(self) -> None:
        check_numbers(f"{self.section}.", self)
        self.check(f"{self.section}.")

    def check(self, at: str) -> None:
        """Refuse bad values; ``at`` is the section's prefix (``continual.lgr.``)."""


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
    names: dict[tuple[str, str], str] = field(default_factory=dict)  # (strategy, scope) -> name
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
        if m.settings is not None:
            m.settings.section = f"{family}.{m.key}"
        table[m.key] = m
    return table


# --------------------------------------------------------------------------- strategies


@dataclass(frozen=True)
class ProxSettings(Settings):
    mu: float = 0.01  # client loss + mu/2 ||w - w_global||^2

    def check(self, at: str) -> None:
        nonnegative(f"{at}mu", self.mu)


@dataclass(frozen=True)
class OptSettings(Settings):
    """FedAdam's server optimiser: x <- x + lr m / (sqrt(v) + tau)."""

    lr: float = 0.01
    betas: tuple[float, float] = (0.9, 0.99)
    tau: float = 1e-3

    def check(self, at: str) -> None:
        if self.lr <= 0 or self.tau <= 0:
            raise ConfigError(f"{at}lr and {at}tau must be > 0")
        check_betas(f"{at}betas", self.betas)


@dataclass(frozen=True)
class DistillSettings(Settings):
    weight: float = 0.5  # weight of the teacher term in the student loss

    def check(self, at: str) -> None:
        if not 0.0 <= self.weight <= 1.0:
            raise ConfigError(f"{at}weight={self.weight}: must be in 0..1")


@dataclass(frozen=True)
class AvgMSettings(Settings):
    """Server momentum on the mean update: v <- momentum v + Delta; x <- x + lr v. The
    default keeps Hsu et al.'s effective learning rate lr / (1 - momentum) at 1: lr 1 with
    momentum 0.9 diverged on the demo (docs/methods.md)."""

    momentum: float = 0.9
    lr: float = 0.1

    def check(self, at: str) -> None:
        if not 0.0 <= self.momentum < 1.0:
            raise ConfigError(f"{at}momentum={self.momentum}: must be in [0, 1)")
        if self.lr <= 0:
            raise ConfigError(f"{at}lr={self.lr}: must be > 0")


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
)


# --------------------------------------------------------------------------- continual


@dataclass(frozen=True)
class EWCSettings(Settings):
    """EWC and EWC-Online: lambda_ * sum F (theta - theta*)^2."""

    lambda_: float = 100.0
    fisher: str = "empirical"  # empirical: gradients of the MSE to the labels | model
    gamma: float = 0.9  # EWC-Online: decay of the running Fisher

    def check(self, at: str) -> None:
        nonnegative(f"{at}lambda_", self.lambda_)
        choice(f"{at}fisher", self.fisher, ("empirical", "model"))
        if not 0.0 <= self.gamma <= 1.0:
            raise ConfigError(f"{at}gamma={self.gamma}: must be in 0..1")


@dataclass(frozen=True)
class SISettings(Settings):
    c: float = 1.0  # penalty coefficient
    xi: float = 0.1  # damping

    def check(self, at: str) -> None:
        nonnegative(f"{at}c", self.c)
        nonnegative(f"{at}xi", self.xi)


@dataclass(frozen=True)
class MASSettings(Settings):
    lambda_: float = 1.0  # penalty coefficient

    def check(self, at: str) -> None:
        nonnegative(f"{at}lambda_", self.lambda_)


@dataclass(frozen=True)
class NRSettings(Settings):
    memory: int = 100  # scenes kept per client (all past tasks together)
    replay_ratio: float = 0.5  # memory samples added per current sample in a batch

    def check(self, at: str) -> None:
        nonnegative(f"{at}memory", self.memory)
        nonnegative(f"{at}replay_ratio", self.replay_ratio)


@dataclass(frozen=True)
class LwFSettings(Settings):
    """LwF for regression: loss + alpha * mean (f(x) - f_start(x))^2 from the second task."""

    alpha: float = 1.0

    def check(self, at: str) -> None:
        nonnegative(f"{at}alpha", self.alpha)


@dataclass(frozen=True)
class LGRSettings(Settings):
    """FedLGR's latent generative replay (docs/fedlgr.md)."""

    schedule: str = "two_phase"  # two_phase (top, then root) | joint (one pass)
    replay: str = "generator"  # generator | stored (the oracle: real past latents kept)
    freeze_root_bn: bool = True  # root BatchNorm statistics frozen from task 2
    hidden: int = 512  # the VAE's hidden width
    latent: int = 16  # the VAE's latent size
    epochs: int = 300  # the VAE's most epochs at the end of each task
    patience: int = 20  # ... stop after this many epochs without held-out gain (0: never)
    holdout: float = 0.2  # ... share of a task's latents held out (none under 10 latents)
    batch_size: int = 32
    lr: float = 1e-3  # the generator's learning rate
    beta: float = 4.0  # weight of the VAE's KL term
    sampler: str = "posterior"  # VAE codes from a Gaussian fitted to the training codes | prior
    lr_root: float = 1e-5  # the root's learning rate from the second task on (lr_R)
    root_epochs: int | None = 1  # two_phase: root epochs per round (None: train.epochs)
    replay_ratio: float = 4.0  # pseudo-samples per real sample when training the top
    # Keeping replayed latents valid while the root learns (docs/fedlgr.md): none |
    # compensate | distill | compensate+distill. The defaults (distill at weight 10, the
    # last root block trained) are sweeps/fedlgr_drift_image.yaml's and
    # sweeps/fedlgr_distill_image.yaml's best point; none + train_blocks null is the paper's.
    drift: str = "distill"
    compensate_ridge: float = 1.0  # compensate: ridge of the drift map (x mean eigenvalue)
    distill_weight: float = 10.0  # distill: weight of the root's latent distillation term
    train_blocks: int | None = 1  # from task 2 only the root's last k blocks train (null: all)
    replay_layer: str = "latent"  # latent (the root's output) | freeze (the k blocks' input)

    def check(self, at: str) -> None:
        choice(f"{at}schedule", self.schedule, ("two_phase", "joint"))
        choice(f"{at}replay", self.replay, ("generator", "stored"))
        choice(f"{at}sampler", self.sampler, ("posterior", "prior"))
        choice(f"{at}drift", self.drift, ("none", "compensate", "distill", "compensate+distill"))
        choice(f"{at}replay_layer", self.replay_layer, ("latent", "freeze"))
        if not 0.0 <= self.holdout < 1.0:
            raise ConfigError(f"{at}holdout={self.holdout}: must be in [0, 1)")
        if self.replay_layer == "freeze":
            wrong = [
                f"{at}{name}={value}"
                for name, value, ok in (
                    ("train_blocks", self.train_blocks, bool(self.train_blocks)),
                    ("schedule", self.schedule, self.schedule == "joint"),
                    ("drift", self.drift, "compensate" not in self.drift),
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
        for name in ("patience", "root_epochs", "train_blocks"):
            value = getattr(self, name)
            if value is not None and value < 0:
                raise ConfigError(f"{at}{name}={value}: must be >= 0")
        for name in ("hidden", "latent", "batch_size"):
            positive(f"{at}{name}", getattr(self, name))
        check_epochs(f"{at}epochs", self.epochs)
        check_epochs(f"{at}root_epochs", self.root_epochs, least=0)
        for name in ("replay_ratio", "lr", "lr_root", "beta", "distill_weight"):
            nonnegative(f"{at}{name}", getattr(self, name))
        if self.compensate_ridge <= 0:  # clients hold fewer scenes than latent features
            raise ConfigError(
                f"{at}compensate_ridge={self.compensate_ridge}: must be > 0 (the drift map "
                "is fitted on a client's scenes, fewer than the root's features)"
            )


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
    base = SCOPES[scope] + STRATEGIES[strategy].suffix
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


def in_paper(name: str) -> bool:
    """Is the method (a paper name, ``FedRoot-SI``) one of the paper's, made of a strategy
    and a CL method it compares?"""
    strategy, _, continual = {**METHODS, **FCL_METHODS}[name]
    return STRATEGIES[strategy].in_paper and (continual is None or CONTINUAL[continual].in_paper)
