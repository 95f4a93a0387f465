"""How faithful FedLGR's replay is: measured at every task end, per client (docs/fedlgr.md).

* ``fd_latent``: the Fréchet distance between replayed latents and the real root latents of
  the client's scenes of every task seen so far (both standardised by the real latents'
  per-feature mean and standard deviation, so the figure does not depend on the root's
  scale): ||mu_g - mu_r||^2 + Tr(S_g + S_r - 2 (S_g S_r)^1/2). 0 for a replay that draws
  the real latents; about 2 x the feature count for one that knows nothing of them.
* ``recon_mse``: the generator's reconstruction error on held-out latents (posterior mean,
  squared error per standardised feature): 0 is exact, 1 is no better than the mean.
* ``fd_labels``: the Fréchet distance between the top's 8 outputs on replayed latents and
  on the real ones, the top as the task left it (the next task's labeller) - what replay
  would teach, seen from the top.

The real latents of past tasks are read here for the measurement only: a client on a real
deployment would no longer hold them. torchmetrics' FID needs Inception features of
images, so the distance is computed here (float64, via symmetric eigen-decompositions).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch


def _sqrt_psd(matrix: torch.Tensor) -> torch.Tensor:
    values, vectors = torch.linalg.eigh(matrix)
    return (vectors * values.clamp_min(0).sqrt()) @ vectors.T


def frechet_distance(a: torch.Tensor, b: torch.Tensor) -> float:
    """The Fréchet distance between Gaussians fitted to the rows of ``a`` and of ``b``;
    NaN where either has under two rows (a client of one scene: no covariance)."""
    if len(a) < 2 or len(b) < 2:
        return math.nan
    a, b = a.double(), b.double()
    mu_a, mu_b = a.mean(dim=0), b.mean(dim=0)
    cov_a, cov_b = torch.cov(a.T).reshape(a.shape[1], -1), torch.cov(b.T).reshape(b.shape[1], -1)
    root_a = _sqrt_psd(cov_a)
    # Tr((S_a S_b)^1/2) = Tr((S_a^1/2 S_b S_a^1/2)^1/2), symmetric and PSD.
    middle = root_a @ cov_b @ root_a
    trace_sqrt = torch.linalg.eigvalsh((middle + middle.T) / 2).clamp_min(0).sqrt().sum()
    distance = (mu_a - mu_b).pow(2).sum() + cov_a.trace() + cov_b.trace() - 2 * trace_sqrt
    return max(float(distance), 0.0)


def standardise_like(reference: torch.Tensor, *others: torch.Tensor) -> list[torch.Tensor]:
    """Standardised by ``reference``'s per-feature mean and std. Features (almost) constant
    in the reference - dead ReLU units - are scaled as if their std were a tenth of the
    median feature's, so that numerical dust in them does not swamp the distance."""
    mean, std = reference.mean(dim=0), reference.std(dim=0).nan_to_num(0.0)
    live = std[std > 0]
    floor = 0.1 * float(live.median()) if len(live) else 1.0
    return [(t - mean) / std.clamp_min(floor) for t in (reference, *others)]


@torch.no_grad()
def replay_fidelity(
    real: torch.Tensor,
    replayed: torch.Tensor,
    labeller: Callable[[torch.Tensor], torch.Tensor],
    heldout: torch.Tensor | None = None,
    reconstruct: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> dict[str, float]:
    """The fidelity figures of ``replayed`` latents against ``real`` ones (same count is
    best), and of ``reconstruct`` on ``heldout`` latents where both are given."""
    real_s, replayed_s = standardise_like(real, replayed)
    out = {
        "fd_latent": frechet_distance(replayed_s, real_s),
        "fd_labels": frechet_distance(labeller(replayed).float(), labeller(real).float()),
    }
    if reconstruct is not None and heldout is not None and len(heldout):
        held_s, recon_s = standardise_like(real, heldout, reconstruct(heldout))[1:]
        out["recon_mse"] = float((recon_s - held_s).pow(2).mean())
    return out
