"""Client-level differential privacy: DP-FedAvg (McMahan et al., ICLR 2018) with fixed or
adaptive clipping (Andrew et al., NeurIPS 2021), and its accountant.

Each round, every client's update - its shared tensors minus the global ones, and what its
strategy's plugins send (SCAFFOLD's control-variate change), as one vector - is clipped to
the L2 norm ``C`` and counts once (weight 1, not its sample count: the count is data too);
the server adds Gaussian noise of standard deviation ``z * C`` to the sum of the clipped
updates and divides by the expected number of clients in the round, ``q * N`` (the
fixed-denominator estimator of McMahan et al.), so one client changes the released mean by
at most ``C / (q N)`` whatever the others sent. Where ``federated.fraction`` < 1, clients
are sampled as the paper does: each independently with probability ``q`` (Poisson
sampling), so the accountant's sampled Gaussian is exactly the mechanism run, and a round
with no client still releases its noise.

Adaptive clipping (Andrew et al., NeurIPS 2021, Algorithm 1 as TensorFlow Privacy's
``QuantileEstimatorQuery`` runs it): each client also reports ``b - 1/2``, where ``b`` is 1
if its update's norm was at most ``C`` and 0 if not (:func:`centred_bit`); the server
releases the share ``(sum(b - 1/2) + N(0, sigma_b^2)) / (q N) + 1/2`` and moves ``C``
geometrically towards the ``quantile`` of the update norms,
``C <- C * exp(-lr * (share - quantile))``. Adding or removing one client moves the sum of
centred bits by exactly 1/2 (:data:`COUNT_SENSITIVITY`), so the count is a Gaussian of
multiplier ``sigma_b / (1/2) = 2 sigma_b``; the updates' noise multiplier is raised to
``z_u = (z^-2 - (2 sigma_b)^-2)^-1/2`` (:func:`update_multiplier`, their Theorem 1), and the
two releases of a round together are one Gaussian of multiplier
``(z_u^-2 + (2 sigma_b)^-2)^-1/2 = z`` on the same Poisson sample: the accountant's epsilon
for ``z`` is the mechanism's. (Summing 0/1 bits instead would move the count by 1 and
cost more than ``z`` says.)

The accountant is Google's dp-accounting (RDP), for the add-or-remove-one-client relation:
epsilon after ``T`` noisy releases of a Poisson-sampled Gaussian of rate ``q`` and
multiplier ``z`` at ``delta``.

The noise is drawn from a generator seeded by the run's seed and the release's number in
the in-process runtime (every process draws the same, and a resumed run the same again);
in the Flower runtime, where the server runs for real, it is seeded from the operating
system's random source (``os.urandom``) every release. Neither is a cryptographically
secure sampler of the Gaussian (floating-point noise: Mironov, CCS 2012).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
import torch

from fedlgr.core.messages import TrainRes, Weights
from fedlgr.errors import FedlgrError

if TYPE_CHECKING:
    from fedlgr.core.settings import ExperimentConfig

# a client's centred "within the clip norm" bit, b - 1/2 (adaptive clipping), summed with the
# payloads: the sum over clients is the count of updates within the clip norm minus half of them
UNCLIPPED = "dp/unclipped"
COUNT_SENSITIVITY = 0.5  # what one client adds to or takes from the sum of centred bits
_NOISE_TAG = 0xD1FF
_COUNT_TAG = 0xC0DE


def norm(tensors: Mapping[str, torch.Tensor]) -> float:
    """The L2 norm of all ``tensors`` as one vector (float64)."""
    total = sum(float(t.detach().double().pow(2).sum()) for t in tensors.values())
    return math.sqrt(total)


def clip(tensors: Weights, bound: float) -> tuple[Weights, float]:
    """``tensors`` scaled as one vector to an L2 norm of at most ``bound``, and their norm
    before: ``t * min(1, bound / ||t||)``."""
    size = norm(tensors)
    factor = 1.0 if size <= bound else bound / size
    return {k: t * factor for k, t in tensors.items()}, size


def gaussian(like: Mapping[str, torch.Tensor], std: float, generator: torch.Generator) -> Weights:
    """Independent N(0, std^2) noise shaped like each of ``like`` (float64, drawn on the CPU
    in key order so that every device draws the same; then moved to ``like``'s)."""
    return {
        k: (torch.randn(t.shape, dtype=torch.float64, generator=generator).mul_(std).to(t.device))
        for k, t in sorted(like.items())
    }


def generator(seed: int, release: int, tag: int, from_os: bool) -> torch.Generator:
    """The generator of a release's noise: seeded by the run's ``seed``, the release's number
    and what it is for (``tag``), or by 8 bytes of ``os.urandom`` (``from_os``)."""
    made = torch.Generator()
    if from_os:
        made.manual_seed(int.from_bytes(os.urandom(8), "little") >> 1)
    else:
        state = np.random.SeedSequence([seed, release, tag]).generate_state(1, np.uint64)
        made.manual_seed(int(state[0]) >> 1)
    return made


def centred_bit(size: float, bound: float) -> float:
    """What a client reports for adaptive clipping: ``b - 1/2``, with ``b`` 1 if its
    update's norm ``size`` is within the clip norm ``bound``, else 0 (+-1/2: so that one
    client moves the sum by :data:`COUNT_SENSITIVITY`, as Andrew et al.'s Theorem 1 needs)."""
    return 0.5 if size <= bound else -0.5


def update_multiplier(noise_multiplier: float, count_std: float) -> float:
    """The updates' noise multiplier ``z_u`` under adaptive clipping so that the updates
    and the noisy count together cost one Gaussian of ``noise_multiplier`` ``z`` (Andrew et
    al., Th. 1): the count of centred bits has sensitivity 1/2, so its noise ``count_std``
    is a Gaussian of multiplier ``2 count_std``, and ``z_u^-2 + (2 count_std)^-2 = z^-2``;
    ``count_std`` must exceed ``z / 2``."""
    if noise_multiplier == 0:
        return 0.0
    rest = noise_multiplier**-2 - (count_std / COUNT_SENSITIVITY) ** -2
    if rest <= 0:
        raise ValueError(
            f"the count's noise {count_std:g} leaves no budget for the updates: it must be "
            f"over noise_multiplier / 2 = {noise_multiplier / 2:g}"
        )
    return rest**-0.5


def epsilon(noise_multiplier: float, rate: float, releases: int, delta: float) -> float:
    """dp-accounting's RDP epsilon at ``delta`` after ``releases`` Poisson-sampled Gaussians
    of sampling ``rate`` and ``noise_multiplier`` (inf without noise, 0 before any)."""
    if releases == 0:
        return 0.0
    if noise_multiplier == 0:
        return math.inf
    # lazy: dp-accounting (absl, scipy, mpmath) is loaded by runs with DP only
    import dp_accounting
    from dp_accounting import rdp

    event = dp_accounting.SelfComposedDpEvent(
        dp_accounting.PoissonSampledDpEvent(rate, dp_accounting.GaussianDpEvent(noise_multiplier)),
        releases,
    )
    accountant = rdp.RdpAccountant()
    absl = logging.getLogger("absl")
    level = absl.level
    absl.setLevel(logging.ERROR)  # "failed to converge ... excluding this order": its own note
    try:
        return float(accountant.compose(event).get_epsilon(delta))
    finally:
        absl.setLevel(level)


def releases_within(
    target: float, noise_multiplier: float, rate: float, delta: float, most: int
) -> int:
    """The most releases (up to ``most``) whose epsilon stays at or under ``target``."""
    low, high = 0, most  # epsilon grows with the releases: bisect
    while low < high:
        middle = (low + high + 1) // 2
        if epsilon(noise_multiplier, rate, middle, delta) <= target:
            low = middle
        else:
            high = middle - 1
    return low


class Privacy:
    """The server's side of DP-FedAvg for a run: the clip norm (adaptive clipping moves
    it), the noise and the releases so far, which the accountant's epsilon is of."""

    def __init__(self, config: ExperimentConfig, from_os: bool = False):
        self.settings = config.federated.dp
        self.seed, self.from_os = config.seed, from_os
        self.rate = config.federated.fraction
        self.expected = self.rate * config.data.clients  # the fixed denominator, q N
        settings = self.settings
        self.adaptive = settings.clipping == "adaptive"
        self.count_std = settings.count_noise or self.expected / 20  # Andrew et al.'s m / 20
        z = settings.noise_multiplier
        self.multiplier = update_multiplier(z, self.count_std) if self.adaptive else z
        self.bound = settings.clip  # the clip norm now
        self.releases = 0
        # adaptive: the last round's released count, sum(b - 1/2) + N(0, sigma_b^2)
        self.count: float | None = None

    # ------------------------------------------------------------------ on each upload

    def clipped(self, result: TrainRes, shared: Weights) -> TrainRes:
        """``result`` with its update (tensors minus ``shared``, and its payload) clipped
        to the clip norm, weighing 1; its payload says whether it was within the norm,
        as ``b - 1/2`` (``UNCLIPPED``, :func:`centred_bit`: for adaptive clipping)."""
        delta = {k: result.weights[k].double() - shared[k].double() for k in shared}
        update = {f"w/{k}": v for k, v in delta.items()}
        update |= {f"p/{k}": v.double() for k, v in result.payload.items()}
        small, size = clip(update, self.bound)
        weights = {k: shared[k].double() + small[f"w/{k}"] for k in shared}
        payload = {k: small[f"p/{k}"] for k in result.payload}
        device = next(iter(shared.values())).device
        within = torch.tensor(centred_bit(size, self.bound), dtype=torch.float64, device=device)
        return dataclasses.replace(
            result, weights=weights, payload=payload | {UNCLIPPED: within}, n_samples=1
        )

    # ------------------------------------------------------------------ on the sums

    def mean(
        self, sums: Weights, count: float, payloads: Weights, shared: Weights
    ) -> tuple[Weights, Weights]:
        """The release of a round: the global tensors ``shared`` plus the noisy sum of the
        ``count`` clipped updates (``sums``: of their tensors, :meth:`clipped`) over the
        expected clients ``q N``; the payloads' sums with their noise. Adaptive clipping
        then moves the clip norm for the next round from the sum of the clients' centred
        bits (``payloads[UNCLIPPED]``; none: no client)."""
        self.releases += 1
        std = self.multiplier * self.bound
        draw = generator(self.seed, self.releases, _NOISE_TAG, self.from_os)
        payloads = dict(payloads)
        centred = payloads.pop(UNCLIPPED, None)
        noise = gaussian(shared, std, draw)
        mean = {}
        for k, g in shared.items():
            update = noise[k] - count * g.double()
            if k in sums:
                update = update + sums[k]
            mean[k] = (g.double() + update / self.expected).to(g.dtype)
        noise = gaussian(payloads, std, draw)
        payloads = {k: p + noise[k] for k, p in payloads.items()}
        if self.adaptive:
            self.adapt(0.0 if centred is None else float(centred))
        return mean, payloads

    def adapt(self, centred: float) -> float:
        """Move the clip norm towards the target quantile from the noisy share of updates
        that were within it, and return that share. ``centred``: the sum of the clients'
        ``b - 1/2``, which one client moves by 1/2; released with N(0, sigma_b^2) noise
        (:attr:`count`), then over ``q N`` plus 1/2 back (TensorFlow Privacy's
        ``QuantileEstimatorQuery``): post-processing of the release, no further cost."""
        draw = generator(self.seed, self.releases, _COUNT_TAG, self.from_os)
        noise = float(torch.randn((), dtype=torch.float64, generator=draw)) * self.count_std
        self.count = centred + noise
        share = self.count / self.expected + 0.5
        self.bound *= math.exp(-self.settings.clip_lr * (share - self.settings.quantile))
        return share

    # ------------------------------------------------------------------ the record

    @property
    def epsilon(self) -> float:
        """The accountant's epsilon after the releases so far: of one Poisson-sampled
        Gaussian of multiplier ``z`` per release, which is what a release is with fixed
        clipping and, with adaptive clipping, what the updates' noise ``z_u`` and the
        count of centred bits together are (:func:`update_multiplier`)."""
        s = self.settings
        return epsilon(s.noise_multiplier, self.rate, self.releases, s.delta)

    def figures(self) -> dict[str, float]:
        """What a round records: ``privacy/epsilon`` and the clip norm now (``privacy/clip``);
        without noise (clipping alone) no epsilon: there is no guarantee to report."""
        spent = {} if self.settings.noise_multiplier == 0 else {"privacy/epsilon": self.epsilon}
        return spent | {"privacy/clip": self.bound}

    def state_dict(self) -> dict:
        return {"bound": self.bound, "releases": self.releases, "bits": "centred"}

    def load_state_dict(self, state: dict) -> None:
        """The clip norm and the releases so far. An adaptive run checkpointed before its
        bits were centred (no ``bits``) is refused: its releases cost more than the
        accountant's epsilon for ``z``, which it would go on reporting."""
        if self.adaptive and int(state["releases"]) > 0 and state.get("bits") != "centred":
            raise FedlgrError(
                f"this checkpoint's {int(state['releases'])} adaptive-clipping releases "
                "summed 0/1 bits, whose privacy cost is above the epsilon fedlgr reported "
                "for them (docs/privacy.md); start the run again"
            )
        self.bound, self.releases = float(state["bound"]), int(state["releases"])
