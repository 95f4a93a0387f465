"""FedLGR's generator (docs/fedlgr.md): a VAE over the root's latent features.

Encoder: in -> hidden -> hidden -> (mu, log-variance) of a ``latent``-d code; the decoder
mirrors it. Loss: reconstruction (squared error summed over features) + ``beta`` x the KL
divergence to N(0, I), both averaged over the batch. Latents are standardised with the mean
and standard deviation of the data the VAE was last fitted on (buffers), so that the
ReLU6-pooled root features of any scale are learnt alike; ``sample`` returns latents in the
root's scale.

``fit`` trains until the loss on held-out latents stops improving (early stopping with a
patience, the best weights kept): a fixed, short budget (the authors' code: 5 epochs at lr
1e-4) leaves the generator far from the latent distribution (docs/fedlgr.md).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import lightning as L
import torch
from torch import nn


@dataclass
class FitReport:
    """How a ``fit`` went: the losses per epoch, and the epoch whose weights were kept."""

    train: list[float] = field(default_factory=list)
    heldout: list[float] = field(default_factory=list)
    best_epoch: int = 0  # 1-based; 0 when nothing was trained

    @property
    def epochs(self) -> int:
        return len(self.train)


class LatentVAE(L.LightningModule):
    def __init__(
        self,
        in_dim: int = 1280,
        hidden: int = 512,
        latent: int = 64,
        lr: float = 1e-3,
        beta: float = 1.0,
    ):
        super().__init__()
        self.latent, self.lr, self.beta = latent, lr, beta
        self.encoder = nn.Sequential(
            nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
        )
        self.mu = nn.Linear(hidden, latent)
        self.logvar = nn.Linear(hidden, latent)
        self.decoder = nn.Sequential(
            nn.Linear(latent, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, in_dim),
        )
        self.register_buffer("shift", torch.zeros(in_dim))
        self.register_buffer("scale", torch.ones(in_dim))
        # Where codes are drawn from: N(0, I) (the prior), or - with ``fit_code_density`` -
        # a full-covariance Gaussian fitted to the codes of the training latents.
        self.register_buffer("code_mean", torch.zeros(latent))
        self.register_buffer("code_chol", torch.eye(latent))

    def standardise(self, r: torch.Tensor) -> torch.Tensor:
        return (r - self.shift) / self.scale

    def forward(
        self, r: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(reconstruction, mu, logvar), all in standardised units. The reparameterisation
        noise comes from ``generator`` (each client has its own), in training mode only."""
        h = self.encoder(self.standardise(r))
        mu, logvar = self.mu(h), self.logvar(h).clamp(-10.0, 10.0)
        if not self.training:
            return self.decoder(mu), mu, logvar
        eps = torch.randn(mu.shape, generator=generator).to(mu.device)
        return self.decoder(mu + eps * torch.exp(0.5 * logvar)), mu, logvar

    def loss(self, r: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        recon, mu, logvar = self(r, generator)
        rec = (recon - self.standardise(r)).pow(2).sum(dim=1).mean()
        kl = -0.5 * (1 + logvar - mu.pow(2) - logvar.exp()).sum(dim=1).mean()
        return rec + self.beta * kl

    def training_step(
        self, batch: torch.Tensor, batch_idx: int = 0, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        return self.loss(batch, generator)

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.parameters(), lr=self.lr)

    @torch.no_grad()
    def fit_code_density(self, latents: torch.Tensor) -> None:
        """Draw codes from a Gaussian fitted to the posterior means of ``latents`` instead of
        N(0, I) (ex-post density estimation, Ghosh et al. 2020, "From Variational to
        Deterministic Autoencoders"): with a few hundred training latents the aggregate
        posterior does not fill the prior, and prior samples decode off the data. Under two
        latents (a client of one scene in the task) no covariance is estimable: the codes
        stay drawn from the prior."""
        if len(latents) < 2:
            return
        was = self.training
        self.eval()
        codes = self(latents)[1].double()
        self.train(was)
        cov = torch.cov(codes.T).reshape(self.latent, self.latent)
        cov += 1e-6 * torch.eye(self.latent, dtype=cov.dtype, device=cov.device)
        self.code_mean.copy_(codes.mean(dim=0))
        self.code_chol.copy_(torch.linalg.cholesky(cov))

    @torch.no_grad()
    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` pseudo-latents decoded from the code distribution, in the root's scale."""
        eps = torch.randn(n, self.latent, generator=generator).to(self.shift.device)
        z = self.code_mean + eps @ self.code_chol.T
        was = self.training
        self.eval()
        out = self.decoder(z) * self.scale + self.shift
        self.train(was)
        return out

    @torch.no_grad()
    def reconstruct(self, r: torch.Tensor) -> torch.Tensor:
        """Encode to the posterior mean and decode, in the root's scale."""
        was = self.training
        self.eval()
        out = self(r)[0] * self.scale + self.shift
        self.train(was)
        return out

    @torch.no_grad()
    def heldout_loss(self, latents: torch.Tensor) -> float:
        was = self.training
        self.eval()
        loss = float(self.loss(latents))
        self.train(was)
        return loss

    def fit(
        self,
        latents: torch.Tensor,
        epochs: int,
        batch_size: int,
        generator: torch.Generator | None = None,
        heldout: torch.Tensor | None = None,
        patience: int = 0,
    ) -> FitReport:
        """Fit (continue training) on ``latents`` for at most ``epochs`` epochs. With
        ``heldout`` latents and ``patience`` > 0, stop once the held-out loss has not
        improved for ``patience`` epochs and keep the weights of its best epoch."""
        with torch.no_grad():
            self.code_mean.zero_()
            self.code_chol.copy_(torch.eye(self.latent))
            self.shift.copy_(latents.mean(dim=0))
            self.scale.copy_(latents.std(dim=0).nan_to_num(1.0).clamp_min(1e-3))
        optimizer = self.configure_optimizers()
        report = FitReport()
        best, best_state = float("inf"), None
        for epoch in range(1, epochs + 1):
            self.train()
            order = torch.randperm(len(latents), generator=generator).to(latents.device)
            total = 0.0
            for i in range(0, len(latents), batch_size):
                batch = latents[order[i : i + batch_size]]
                loss = self.training_step(batch, generator=generator)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                total += float(loss.detach()) * len(batch)
            report.train.append(total / len(latents))
            if heldout is None or len(heldout) == 0:
                report.best_epoch = epoch
                continue
            report.heldout.append(self.heldout_loss(heldout))
            if report.heldout[-1] < best:
                best, report.best_epoch = report.heldout[-1], epoch
                best_state = copy.deepcopy(self.state_dict())
            elif patience and epoch - report.best_epoch >= patience:
                break
        if best_state is not None:
            self.load_state_dict(best_state)
        self.eval()
        return report
