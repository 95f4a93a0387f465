"""The rules a bound on one setting cannot say: one setting against another, within a
section (called from its ``__post_init__``) and across sections (:func:`experiment`).
Each refusal is one line naming the settings; the bounds are fixed on purpose, and each
message says why. A rule that needs the machine (its memory) is the shell's."""

from __future__ import annotations

from typing import Any

from fedlgr.core.methods import CONTINUAL, STRATEGIES, method_name
from fedlgr.errors import ConfigError

MOBILENET_V2_BLOCKS = 19  # its features' blocks (Root.blocks(); a test checks the model)
SEED_LIMIT = 2**32  # numpy's and Lightning's seeding take 32-bit seeds
MAX_ROUNDS = 1_000_000
ROUNDS_BOUND = (
    f"at most {MAX_ROUNDS} rounds (a fixed bound: each round trains every client and logs to "
    f"MLflow, so at even 1 s a round {MAX_ROUNDS} rounds take 12 days)"
)
MAX_EXPERIMENT_NAME = 500  # MLflow's mlflow.utils.validation.MAX_EXPERIMENT_NAME_LENGTH
MAX_INTERVAL_S = 86_400  # heartbeat and system-metrics intervals (threading.Event.wait)
MAX_PER_MACHINE = 1024  # processes, torch threads or client threads on one machine
PER_MACHINE = (
    "at most {bound} (a fixed bound, more than any machine's cores or GPUs: each is a "
    "process or a thread)"
)
MIN_IMAGE_SIZE, MAX_IMAGE_SIZE = 16, 4096  # the paper trains at 128 px
MAX_AUGMENT_COPIES = 1000  # the paper shows each scene 10 times an epoch
MODULUS = 2**32  # SecAgg+'s masks: sums of quantised values must stay below it


def format_bytes(n: float) -> str:
    """``3.2 GB``: decimal units, as ``free`` and ``df -H`` print them."""
    units = ("B", "kB", "MB", "GB", "TB")
    k = 0
    while n >= 1000 and k < len(units) - 1:
        n, k = n / 1000, k + 1
    return f"{n:.0f} B" if k == 0 else f"{n:.1f} {units[k]}"


# --------------------------------------------------------------------------- within a section


def data(data: Any) -> None:
    size, copies = data.image_size, data.augment_copies
    if size > MAX_IMAGE_SIZE:
        raise ConfigError(
            f"data.image_size={size}: at most {MAX_IMAGE_SIZE} (a fixed bound: each scene "
            f"takes 3 x size^2 bytes in the decoded image store and 12 x size^2 as float32 in "
            f"a batch, {format_bytes(3 * size**2)} and {format_bytes(12 * size**2)} here; "
            "the paper trains at 128 px)"
        )
    if copies > MAX_AUGMENT_COPIES:
        raise ConfigError(
            f"data.augment_copies={copies}: at most {MAX_AUGMENT_COPIES} (a fixed bound: an "
            "augmented epoch shows each training scene this many times, and its shuffled "
            f"order takes 24 bytes per showing, {format_bytes(24 * copies)} per scene here; "
            "the paper uses 10)"
        )
    if data.modality == "image" and data.noise != type(data.noise)():
        raise ConfigError(
            "data.noise: the descriptors' noise, for data.modality=features; images are "
            "flipped and rotated instead (data.augment, data.augment_copies)"
        )
    names = [t.name for t in data.tasks]
    if not names:
        raise ConfigError("data.tasks: need at least one task")
    if len(set(names)) != len(names):
        raise ConfigError(f"data.tasks: task names must be unique, got {names}")
    if data.crop is not None:
        _crop(data.crop)


def _crop(crop: Any) -> None:
    """``[left, top, right, bottom]`` source pixels, each >= 0 or null for an image edge."""
    if len(crop) != 4 or not all(v is None or v >= 0 for v in crop):
        raise ConfigError(
            f"data.crop={list(crop)}: must be [left, top, right, bottom] "
            "pixel positions (>= 0) or null for an image edge"
        )
    left, top, right, bottom = crop
    if left is not None and right is not None and right <= left:
        raise ConfigError(f"data.crop={list(crop)}: right ({right}) must exceed left ({left})")
    if top is not None and bottom is not None and bottom <= top:
        raise ConfigError(f"data.crop={list(crop)}: bottom ({bottom}) must exceed top ({top})")


def model(model: Any) -> None:
    if model.weights == "imagenet" and model.width != 1.0:
        raise ConfigError(
            f"model.weights=imagenet needs model.width=1.0 (got {model.width}): "
            "the ImageNet weights exist only for the full-width MobileNetV2"
        )
    if not model.mlp_hidden or min(model.mlp_hidden) < 1:
        raise ConfigError(f"model.mlp_hidden={list(model.mlp_hidden)}: need >= 1 positive size")


def federated(federated: Any) -> None:
    if federated.norm_ratio != 0 and federated.norm_ratio < 1:
        raise ConfigError(
            f"federated.norm_ratio={federated.norm_ratio}: must be 0 (no check) or at least 1 "
            "(an update over this many times the round's median update norm is refused)"
        )
    if federated.count_cap != 0 and federated.count_cap < 1:
        raise ConfigError(
            f"federated.count_cap={federated.count_cap:g}: must be 0 (no cap) or at least 1 "
            "(a robot's sample count is capped at this many times the others' median)"
        )


def dp(dp: Any) -> None:
    if dp.target_epsilon > 0 and dp.noise_multiplier == 0:
        raise ConfigError(
            f"federated.dp.target_epsilon={dp.target_epsilon:g} needs noise: with "
            "federated.dp.noise_multiplier=0 epsilon is infinite from the first round"
        )


def tracking(tracking: Any) -> None:
    if not tracking.experiment:
        raise ConfigError("tracking.experiment: must not be empty")
    if len(tracking.experiment) > MAX_EXPERIMENT_NAME:
        raise ConfigError(
            f"tracking.experiment: {len(tracking.experiment)} characters, MLflow allows at "
            f"most {MAX_EXPERIMENT_NAME} (mlflow.utils.validation.MAX_EXPERIMENT_NAME_LENGTH)"
        )


def continual(continual: Any) -> None:
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


# --------------------------------------------------------------------------- across sections


def experiment(config: Any) -> None:
    """The rules across sections, after each section has checked its own."""
    _rounds_in_all(config)
    _method_fits(config)
    _tasks_known(config)
    _root_reads_features(config)
    _processes_have_clients(config)
    _root_reads_images(config)
    _train_blocks(config)
    _privacy_fits(config)
    _secure_aggregation_fits(config)
    _robust_within_its_bound(config)


def _rounds_in_all(config: Any) -> None:
    """A task schedule's rounds, all tasks together, within MAX_ROUNDS."""
    if config.continual.tasks and config.total_rounds > MAX_ROUNDS:
        raise ConfigError(
            f"continual.rounds_per_task={config.continual.rounds_per_task} x "
            f"{len(config.continual.tasks)} tasks = {config.total_rounds} rounds: "
            f"{ROUNDS_BOUND}"
        )


def _method_fits(config: Any) -> None:
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


def _tasks_known(config: Any) -> None:
    known = [t.name for t in config.data.tasks]
    unknown = [t for t in config.continual.tasks if t not in known]
    if unknown:
        raise ConfigError(f"continual.tasks: unknown task(s) {unknown}; data.tasks has {known}")


def _root_reads_features(config: Any) -> None:
    if config.data.modality == "features" and config.root_kind != "mlp":
        raise ConfigError(
            f"model.root={config.model.root} reads images, but data.modality=features: "
            "use model.root=mlp (or auto)"
        )


def _processes_have_clients(config: Any) -> None:
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


def _root_reads_images(config: Any) -> None:
    if config.data.modality == "image" and config.root_kind == "mlp":
        raise ConfigError("model.root=mlp reads the descriptors: set data.modality=features")


def _train_blocks(config: Any) -> None:
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


def _secure_aggregation_fits(config: Any) -> None:
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


def _privacy_fits(config: Any) -> None:
    """Client-level DP (``federated.dp``) bounds what one client adds to a weighted sum:
    a statistic of the uploads (a median, Krum's choice) has no such bound; adaptive
    clipping's count noise must leave budget for the updates (over ``z / 2``: the count of
    centred bits, :func:`fedlgr.core.privacy.update_multiplier`); delta below 1 / clients."""
    dp, federated = config.federated.dp, config.federated
    if not dp.enabled:
        if dp.target_epsilon > 0:
            raise ConfigError(
                f"federated.dp.target_epsilon={dp.target_epsilon:g} with DP off "
                "(federated.dp.clip=0): there is no privacy budget to stop at; set "
                "federated.dp.clip, or leave the target out"
            )
        return
    if _aggregates_a_statistic(federated):
        raise ConfigError(
            f"federated.dp.clip={dp.clip:g} with federated.strategy={federated.strategy}: "
            "DP-FedAvg bounds one client's effect on the mean of clipped updates, and a "
            f"{federated.strategy} aggregate of the uploads has no such bound (one client "
            f"can move it arbitrarily far in L2); {mean_based()}"
        )
    clients = config.data.clients
    if federated.fraction * clients < 1:
        raise ConfigError(
            f"federated.fraction={federated.fraction:g} with data.clients={clients}: "
            f"{federated.fraction * clients:g} expected clients a round under DP; DP-FedAvg "
            "divides the noised sum by that fixed count, so below 1 the noise is blown up "
            "and most rounds average nobody: sample at least one client a round"
        )
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
    _target_fits_a_round(config)


def _target_fits_a_round(config: Any) -> None:
    """A privacy target that round 1 alone exceeds would stop the run before it trains."""
    dp = config.federated.dp
    if not dp.target_epsilon > 0 or dp.noise_multiplier == 0:
        return
    from fedlgr.core.privacy import epsilon  # lazy: torch and dp-accounting, for DP targets only

    first = epsilon(dp.noise_multiplier, config.federated.fraction, 1, dp.delta)
    if first > dp.target_epsilon:
        raise ConfigError(
            f"federated.dp.target_epsilon={dp.target_epsilon:g}: round 1 alone spends epsilon "
            f"{first:.3g} (noise_multiplier={dp.noise_multiplier:g}, "
            f"fraction={config.federated.fraction:g}, delta={dp.delta:g}), so the run would "
            "stop before it trains; raise the target or the noise"
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


def _robust_within_its_bound(config: Any) -> None:
    """A robust aggregate within what it tolerates: Multi-Krum keeps at most n - f uploads
    (Blanchard et al. 2017), and simulated attackers stay below the median's half, within
    the trimmed mean's cut and Krum's ``f``; beyond, the run is no test of the method."""
    federated, clients = config.federated, config.data.clients
    strategy, attackers = federated.strategy, federated.faults.byzantine
    # as many as core/strategies/base.participants draws (not imported here: torch)
    uploads = clients if federated.fraction >= 1 else max(1, round(federated.fraction * clients))
    krum, a_round = federated.krum, f"{uploads} upload{'s' * (uploads != 1)} a round"
    if strategy == "krum" and krum.m > 1 and krum.m > uploads - krum.f:
        raise ConfigError(
            f"federated.krum.m={krum.m} with {a_round} and federated.krum.f={krum.f}: "
            f"Multi-Krum averages the m best-scored uploads, at most n - f = "
            f"{uploads - krum.f} (Blanchard et al. 2017); more takes attackers' uploads in"
        )
    # per round, as the strategies aggregate: every attacker may be drawn into one round
    tolerated = {
        "median": ((uploads - 1) // 2, "fewer than half of them"),
        "trimmed": (
            int(federated.trimmed.beta * uploads),
            f"federated.trimmed.beta={federated.trimmed.beta:g} of them cut at each end",
        ),
        "krum": (krum.f, "federated.krum.f"),
    }
    if strategy in tolerated and attackers > tolerated[strategy][0]:
        most, bound = tolerated[strategy]
        raise ConfigError(
            f"federated.faults.byzantine={attackers} of data.clients={clients}, {a_round}: "
            f"federated.strategy={strategy} tolerates at most {most} ({bound}); beyond its "
            "bound the run measures no robustness"
        )
