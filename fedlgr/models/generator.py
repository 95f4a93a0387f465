"""FedLGR's generator (SPEC 3): a VAE over the root's latent features.

Encoder: in -> hidden -> hidden -> (mu, log-variance) of a ``latent``-d code; the decoder
mirrors it. Loss: reconstruction (squared error summed over features) + KL divergence to
N(0, I), both averaged over the batch. Latents are standardised with the mean and standard
deviation of the data the VAE was last fitted on (buffers), so that the ReLU6-pooled root
features of any scale are learnt alike; ``sample`` returns latents in the root's scale.
"""

from __future__ import annotations

import lightning as L
import torch
from torch import nn


class LatentVAE(L.LightningModule):
    def __init__(self, in_dim: int = 1280, hidden: int = 512, latent: int = 64, lr: float = 1e-4):
        super().__init__()
        self.latent, self.lr = latent, lr
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

    def forward(
        self, r: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(reconstruction, mu, logvar), all in standardised units. The reparameterisation
        noise comes from ``generator`` (each client has its own), in training mode only."""
        h = self.encoder((r - self.shift) / self.scale)
        mu, logvar = self.mu(h), self.logvar(h).clamp(-10.0, 10.0)
        if not self.training:
            return self.decoder(mu), mu, logvar
        eps = torch.randn(mu.shape, generator=generator).to(mu.device)
        return self.decoder(mu + eps * torch.exp(0.5 * logvar)), mu, logvar

    def loss(self, r: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        recon, mu, logvar = self(r, generator)
        target = (r - self.shift) / self.scale
        rec = (recon - target).pow(2).sum(dim=1).mean()
        kl = -0.5 * (1 + logvar - mu.pow(2) - logvar.exp()).sum(dim=1).mean()
        return rec + kl

    def training_step(
        self, batch: torch.Tensor, batch_idx: int = 0, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        return self.loss(batch, generator)

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.parameters(), lr=self.lr)

    @torch.no_grad()
    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` pseudo-latents decoded from N(0, I), in the root's scale."""
        z = torch.randn(n, self.latent, generator=generator).to(self.shift.device)
        was = self.training
        self.eval()
        out = self.decoder(z) * self.scale + self.shift
        self.train(was)
        return out

    def fit(
        self,
        latents: torch.Tensor,
        epochs: int,
        batch_size: int,
        generator: torch.Generator | None = None,
    ) -> list[float]:
        """Fit (continue training) on ``latents``; the mean loss of each epoch."""
        with torch.no_grad():
            self.shift.copy_(latents.mean(dim=0))
            self.scale.copy_(latents.std(dim=0).clamp_min(1e-3))
        optimizer = self.configure_optimizers()
        self.train()
        history = []
        for _ in range(epochs):
            order = torch.randperm(len(latents), generator=generator).to(latents.device)
            total = 0.0
            for i in range(0, len(latents), batch_size):
                batch = latents[order[i : i + batch_size]]
                loss = self.training_step(batch, generator=generator)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                total += float(loss.detach()) * len(batch)
            history.append(total / len(latents))
        return history
