"""Latent drift in FedLGR: how far the root's latents move in a later task, and a map that
carries replayed latents along (docs/fedlgr.md).

FedLGR replays latents of past tasks - the generator's, or the stored oracle's real ones -
in the space of the root as it was when they were learnt. From the second task on the root
trains (at ``continual.lgr.lr_root``) and FedRoot aggregation moves it again, so the
latents of the same scene drift, and replay teaches the top a space the root has left.

* :func:`drift_distance`: the standardised Fréchet distance between the latents of the same
  scenes under two roots (``fedlgr.core.continual.fidelity``'s distance, standardised by the
  current root's latents as ``lgr/fd_latent`` is). 0: no drift.
* :class:`DriftMap` / :func:`fit_drift_map`: learned drift compensation (Iscen et al., ECCV
  2020, "memory-efficient incremental learning through feature adaptation"; Gomez-Villa et
  al. 2024, "LDC"): an affine map from the latents under the root at the task's start to
  the latents under the root now, fitted on the client's *current* scenes (it has both) and
  applied to the replayed latents of past tasks. Ridge regression in closed form, shrunk
  towards the identity rather than towards 0: directions the current scenes do not span
  are left where they were instead of being zeroed (a few hundred scenes vs 1280 features).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from fedlgr.core.continual.fidelity import frechet_distance, standardise_like


def drift_distance(now: torch.Tensor, then: torch.Tensor) -> float:
    """The standardised Fréchet distance between ``then`` and ``now`` (latents of the same
    scenes), both standardised by ``now``'s per-feature mean and std."""
    now_s, then_s = standardise_like(now, then)
    return frechet_distance(then_s, now_s)


@dataclass
class DriftMap:
    """``map(r) = mu_now + (r - mu_then) (I + A)``: latents of the old root into the space of
    the current one."""

    mu_then: torch.Tensor  # (d,)
    mu_now: torch.Tensor  # (d,)
    delta: torch.Tensor  # A, (d, d)

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        centred = r.to(self.delta.dtype) - self.mu_then
        return (self.mu_now + centred + centred @ self.delta).to(r.dtype)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"mu_then": self.mu_then, "mu_now": self.mu_now, "delta": self.delta}


def fit_drift_map(then: torch.Tensor, now: torch.Tensor, ridge: float) -> DriftMap:
    """The map that takes ``then`` (n x d latents of n scenes under the old root) closest to
    ``now`` (the same scenes under the current root) in least squares, with the penalty
    ``lambda ||A||^2`` on its departure A from the identity; ``lambda = ridge`` x the mean
    eigenvalue of the centred ``then``'s scatter matrix, so ``ridge`` does not depend on the
    latents' scale. Solved in float64, in the primal (d x d) form where n > d and in the dual
    (n x n) form otherwise (the same solution for ``ridge > 0``); ``ridge = 0`` with n > d is
    ordinary least squares, which recovers an exactly affine drift exactly (in the float64
    solve; the map keeps ``then``'s dtype)."""
    if then.shape != now.shape or then.dim() != 2:
        raise ValueError(f"latents of the same scenes expected, got {then.shape} / {now.shape}")
    x, y = then.double(), now.double()
    mu_then, mu_now = x.mean(dim=0), y.mean(dim=0)
    xc, dc = x - mu_then, (y - mu_now) - (x - mu_then)
    n, d = xc.shape
    lam = ridge * float(xc.pow(2).sum()) / d
    if n > d:
        scatter = xc.T @ xc + lam * torch.eye(d, dtype=xc.dtype, device=xc.device)
        delta = torch.linalg.solve(scatter, xc.T @ dc)
    else:
        if lam <= 0:
            raise ValueError(f"ridge must be > 0 with {n} scenes for {d} features")
        gram = xc @ xc.T + lam * torch.eye(n, dtype=xc.dtype, device=xc.device)
        delta = xc.T @ torch.linalg.solve(gram, dc)
    # Applied in the latents' own dtype (float32): a replayed batch goes through it at every
    # step of the top, and float64 matrix products cost ~2x on a CPU.
    return DriftMap(*(t.to(then.dtype) for t in (mu_then, mu_now, delta)))
