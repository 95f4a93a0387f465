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
from typing import Any, Literal

from fedlgr.core.declare import (
    Bool,
    Float,
    Int,
    betas,
    epoch_count,
    renamed,
    section,
    setting,
)
from fedlgr.errors import ConfigError


@dataclass(frozen=True)
class Method:
    """One registered method."""

    key: str  # its config value: federated.strategy=prox, continual.method=ewc
    suffix: str  # its part of the paper's name: Prox, EWC
    target: str | None  # "module:Class", imported by load(); None: no class (continual none)
    paper: str = ""  # the publication it follows
    settings: type | None = None  # under federated.<key> / continual.<key>
    uses: str | None = None  # another method's settings section (EWC-Online uses ewc's)
    scopes: tuple[str, ...] = ("full", "root")  # the aggregation scopes it works with
    # (strategy, scope) -> its name where it is not the scope's prefix + suffix (FedLGR)
    names: dict[tuple[str, str], str] = field(default_factory=dict)
    in_paper: Bool = True  # a row of the paper's tables (else a report shows it where it ran)

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
            renamed(m.settings, f"{family}.{m.key}.")
        table[m.key] = m
    return table


# --------------------------------------------------------------------------- strategies


@section("")
class ProxSettings:
    mu: Float = setting(0.01, "client loss + mu/2 ||w - w_global||^2", ge=0)


@section("")
class OptSettings:
    """FedOpt's server optimiser (Reddi et al. 2021, Algorithm 2): x <- x + lr m / (sqrt(v)
    + tau), v by the variant (FedAdam, FedYogi, FedAdagrad; adagrad reads betas[0] only)."""

    lr: Float = setting(0.01, "the server's learning rate", gt=0)
    betas: tuple[Float, Float] = setting((0.9, 0.99), "the moments' decay rates, each in [0, 1)")
    tau: Float = setting(1e-3, "the adaptivity", gt=0)
    variant: Literal["adam", "yogi", "adagrad"] = setting("adam", "FedAdam, FedYogi, FedAdagrad")
    v0: Literal["tau2", "zero"] = setting(
        "tau2", "the second moment's start: the paper's tau^2, or zero (fedlgr's earlier form)"
    )

    def __post_init__(self) -> None:
        betas("federated.opt.betas", self.betas)


@section("")
class DistillSettings:
    weight: Float = setting(0.5, "the teacher term's weight in the student loss", ge=0, le=1)


@section("")
class AvgMSettings:
    """Server momentum on the mean update: v <- momentum v + Delta; x <- x + lr v. The
    default keeps Hsu et al.'s effective learning rate lr / (1 - momentum) at 1: lr 1 with
    momentum 0.9 diverged on the demo (docs/methods.md)."""

    momentum: Float = setting(0.9, "the server's momentum", ge=0, lt=1)
    lr: Float = setting(0.1, "the server's learning rate", gt=0)


@section("")
class ScaffoldSettings:
    lr: Float = setting(1.0, "the global learning rate", gt=0)


@section("")
class TrimmedSettings:
    beta: Float = setting(0.2, "the fraction cut at either end", ge=0, lt=0.5)


@section("")
class KrumSettings:
    f: Int = setting(1, "Byzantine clients Krum tolerates", ge=0)
    m: Int = setting(1, "uploads kept and averaged (Multi-Krum; 1: Krum)", ge=1)


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
        ScaffoldSettings,
        names={("scaffold", "full"): "SCAFFOLD"},
        in_paper=False,
    ),
    Method("median", "Median", f"{STRATEGY}.median:FedMedian", "Yin et al. 2018", in_paper=False),
    Method(
        "trimmed",
        "TrimmedAvg",
        f"{STRATEGY}.trimmed:FedTrimmedAvg",
        "Yin et al. 2018",
        TrimmedSettings,
        in_paper=False,
    ),
    Method(
        "krum",
        "Krum",
        f"{STRATEGY}.krum:Krum",
        "Blanchard et al. 2017",
        KrumSettings,
        names={("krum", "full"): "Krum"},
        in_paper=False,
    ),
)


# --------------------------------------------------------------------------- continual


@section("")
class EWCSettings:
    """EWC and EWC-Online: lambda_ / 2 * sum F (theta - theta*)^2. The default lambda is
    sweeps/ewc.yaml's best on the synthetic descriptors (docs/fedlgr.md, "EWC's lambda")."""

    lambda_: Float = setting(1000.0, "the penalty's coefficient", ge=0)
    fisher: Literal["empirical", "model", "batch", "batch_model"] = setting(
        "empirical",
        "each scene's squared gradient averaged over the task's scenes, of its MSE to the "
        "labels (empirical, Kirkpatrick et al.'s) or to outputs + N(0, 4) noise (model); "
        "batch, batch_model: each mini-batch's, no 1/2 in the penalty (fedlgr's earlier form)",
    )
    gamma: Float = setting(0.9, "EWC-Online: the running Fisher's decay", ge=0, le=1)


@section("")
class SISettings:
    c: Float = setting(1.0, "the penalty's coefficient", ge=0)
    xi: Float = setting(0.1, "the damping", ge=0)
    clamp: Literal["none", "task", "total"] = setting(
        "none",
        "none (Zenke et al.'s eq. 5) | task (each task's gain clamped at 0: fedlgr's earlier "
        "form) | total (the summed importance clamped at 0: the authors' code)",
    )
    path_gradient: Literal["loss", "loss+penalty"] = setting(
        "loss",
        "the gradient in the path integral: without SI's penalty (as published) or with it "
        "(fedlgr's earlier form)",
    )


@section("")
class MASSettings:
    lambda_: Float = setting(1.0, "the penalty's coefficient", ge=0)
    importance: Literal["sample", "batch"] = setting(
        "sample",
        "|gradient of each scene's squared output norm|, averaged (Aljundi et al.'s), or of "
        "each mini-batch's mean (fedlgr's earlier form)",
    )


@section("")
class NRSettings:
    memory: Int = setting(100, "scenes kept per client (all past tasks together)", ge=0)
    replay_ratio: Float = setting(0.5, "memory samples per current sample in a batch", ge=0)


@section("")
class LwFSettings:
    """LwF for regression: loss + alpha * mean (f(x) - f_start(x))^2 from the second task."""

    alpha: Float = setting(1.0, "the distillation term's weight", ge=0)


@section("")
class LGRSettings:
    """FedLGR's latent generative replay (docs/fedlgr.md). ``replay_layer=freeze`` has a
    rule across settings, checked with the config: it needs ``train_blocks`` >= 1,
    ``schedule=joint`` and no compensation. The drift defaults (distill at weight 10, the
    last root block trained) are sweeps/fedlgr_drift_image.yaml's and
    sweeps/fedlgr_distill_image.yaml's best point; none + train_blocks null is the paper's."""

    schedule: Literal["two_phase", "joint"] = setting(
        "two_phase", "two_phase (the top, then the root) | joint (one pass)"
    )
    replay: Literal["generator", "stored"] = setting(
        "generator", "generator | stored (the oracle: real past latents kept)"
    )
    freeze_root_bn: Bool = setting(True, "root BatchNorm statistics frozen from task 2")
    hidden: Int = setting(512, "the VAE's hidden width", ge=1)
    latent: Int = setting(16, "the VAE's latent size", ge=1)
    epochs: Int = epoch_count(300, "the VAE's most epochs at the end of each task")
    patience: Int = setting(
        20, "... stop after this many epochs without held-out gain (0: never)", ge=0
    )
    holdout: Float = setting(
        0.2, "... the share of a task's latents held out (none under 10 latents)", ge=0, lt=1
    )
    batch_size: Int = setting(32, "the VAE's batch size", ge=1)
    lr: Float = setting(1e-3, "the generator's learning rate", ge=0)
    beta: Float = setting(4.0, "the VAE's KL term's weight", ge=0)
    sampler: Literal["posterior", "prior"] = setting(
        "posterior", "VAE codes from a Gaussian fitted to the training codes, or the prior"
    )
    lr_root: Float = setting(1e-5, "the root's learning rate from task 2 on (lr_R)", ge=0)
    root_epochs: Int | None = epoch_count(
        1, "two_phase: root epochs per round (null: train.epochs)", 0
    )
    replay_ratio: Float = setting(4.0, "pseudo-samples per real sample for the top", ge=0)
    drift: Literal["none", "compensate", "distill", "compensate+distill"] = setting(
        "distill", "keeping replayed latents valid while the root learns (docs/fedlgr.md)"
    )
    compensate_ridge: Float = setting(
        1.0,
        "compensate: the drift map's ridge (x mean eigenvalue)",
        gt=0,
        why="the drift map is fitted on a client's scenes, fewer than the root's features",
    )
    distill_weight: Float = setting(10.0, "distill: the latent distillation's weight", ge=0)
    train_blocks: Int | None = setting(
        1, "from task 2 only the root's last k blocks train (null: all)", ge=0
    )
    replay_layer: Literal["latent", "freeze"] = setting(
        "latent", "latent (the root's output) | freeze (the k blocks' input)"
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
