"""FedLGR's client side: latent generative replay (the paper's Algorithm 1, SPEC 4.2).

FedLGR = FedRoot aggregation (scope ``root``) + this plugin on every client:

* in a round of a later task, each batch's loss becomes the MSE over the union of the
  current samples ``<R, y>`` (R = root(x)) and ``replay_ratio`` pseudo-samples per current
  sample ``<R', T'>``: R' decoded by the client's generator from N(0, I), T' = top(R')
  given by the top *as it was before this task's updates* (a frozen copy taken when the
  task starts). R' carries no gradient, so the root learns from the current data only
  and the top from both;
* from the second task on, the root trains at ``lgr_lr_root`` (lr_R, 1e-5) while the top
  keeps ``train.lr_top`` (lr_T): on the first task there is nothing to protect yet;
* at the end of each task the generator (a VAE over root latents) is trained on the latents
  R of the task's scenes (first task), or on R together with as many pseudo-latents R' per
  past task from the generator as it was (later tasks).

Deviation from Algorithm 1, stated: the paper updates the generator inside every batch; the
SPEC (which this project follows where the two differ) trains it at the end of each task.
Root and top are updated from one backward pass rather than one after the other.
The generator and the top never leave the client: with scope ``root`` the upload is the
root alone.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from fedlgr.federated.plugins import ClientPlugin, LocalContext
from fedlgr.models.generator import LatentVAE


class LatentReplay(ClientPlugin):
    name = "lgr"

    def __init__(
        self,
        *,
        hidden: int = 512,
        latent: int = 64,
        epochs: int = 50,
        batch_size: int = 32,
        lr: float = 1e-4,
        lr_root: float = 1e-5,
        replay_ratio: float = 1.0,
        seed: int = 0,
    ):
        self.hidden, self.latent, self.epochs, self.batch_size = hidden, latent, epochs, batch_size
        self.lr, self.lr_root, self.replay_ratio = lr, lr_root, replay_ratio
        self.generator_rng = torch.Generator().manual_seed(seed)
        self.generator: LatentVAE | None = None
        self.labeller: nn.Module | None = None  # the top before this task's updates
        self.tasks_learnt = 0
        self.history: list[float] = []  # the generator's loss per epoch at the last task end

    def on_task_start(self, ctx: LocalContext) -> None:
        if self.generator is not None:
            self.labeller = copy.deepcopy(ctx.model.top).eval().requires_grad_(False)

    def on_round_start(self, ctx: LocalContext) -> None:
        # Every round (a fresh optimiser, train.reset_optimizer=true, starts at train.lr_root).
        if self.generator is not None:
            for group in ctx.optimizer.param_groups:
                if group.get("name") == "root":
                    group["lr"] = self.lr_root

    @torch.no_grad()
    def pseudo_samples(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``n`` pseudo-latents R' and their labels T' from the pre-update top."""
        latents = self.generator.sample(n, self.generator_rng)
        return latents, self.labeller(latents).float()

    def loss(self, ctx, x, y, outputs, loss):
        n = round(len(x) * self.replay_ratio)
        if self.generator is None or n == 0:
            return loss
        latents, labels = self.pseudo_samples(n)
        replay = nn.functional.mse_loss(ctx.model.top(latents).float(), labels)
        # The MSE over the union of the current batch and the pseudo-samples.
        return (loss * len(x) + replay * n) / (len(x) + n)

    @torch.no_grad()
    def latents(self, ctx: LocalContext) -> torch.Tensor:
        root, was = ctx.model.root, ctx.model.root.training
        root.eval()
        try:
            return torch.cat([root(x).float() for x, _ in ctx.plain_batches()])
        finally:
            root.train(was)

    def on_task_end(self, ctx: LocalContext) -> None:
        current = self.latents(ctx)
        if self.generator is None:
            self.generator = LatentVAE(current.shape[1], self.hidden, self.latent, self.lr).to(
                current.device
            )
            data = current
        else:  # R U R': as many pseudo-latents per past task as the task has scenes
            data = torch.cat(
                [
                    current,
                    self.generator.sample(len(current) * self.tasks_learnt, self.generator_rng),
                ]
            )
        with torch.enable_grad():
            self.history = self.generator.fit(
                data, self.epochs, self.batch_size, self.generator_rng
            )
        self.tasks_learnt += 1
        self.labeller = None

    def state_dict(self) -> dict:
        return {
            "generator": None if self.generator is None else self.generator.state_dict(),
            "labeller": None if self.labeller is None else self.labeller.state_dict(),
            "tasks_learnt": self.tasks_learnt,
            "rng": self.generator_rng.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        if state.get("generator") is not None and self.generator is not None:
            self.generator.load_state_dict(state["generator"])
        self.tasks_learnt = state.get("tasks_learnt", 0)
        if "rng" in state:
            self.generator_rng.set_state(state["rng"])
