"""FedLGR's client side: latent generative replay (the paper's Algorithm 1, SPEC 4.2).

FedLGR = FedRoot aggregation (scope ``root``) + this plugin on every client. In Task 1 the
client trains as FedRoot does. At the end of every task its generator (a VAE over root
latents, ``fedlgr.models.generator``) learns the latents R of the task's scenes, together
with as many pseudo-latents R' per past task from the generator as it was. In every round
of a later task:

1. the root trains at ``lgr_lr_root`` (lr_R), the top at ``train.lr_top``, and - with
   ``lgr_freeze_root_bn`` (``fedlgr.continual.batchnorm``) - the root's BatchNorm
   statistics stay as they were after Task 1, so the latent space the generator learnt
   stays put;
2. ``replay_ratio`` pseudo-latents R' per real sample are drawn and labelled T' = top(R')
   by the top *as it was when the task began* (a frozen copy, eval mode);
3. the top trains on <R, y> U <R', T'> **as one batch**: its BatchNorm sees the union;
   the root learns from the current data only. ``lgr_schedule`` says how:

   * ``two_phase`` (the authors' code): first the top alone, for ``train.epochs`` epochs
     over the current scenes' latents - computed once per round, root in eval mode, one
     pass of the client's batches (augmented if augmentation is on) - each batch with its
     pseudo-samples; then the root alone, at lr_R on the current data with the top frozen
     (eval mode, no gradients), for ``lgr_root_epochs`` epochs (default 1; ``None``:
     ``train.epochs`` as in the authors' code; none when lr_R is 0);
   * ``joint``: one pass per batch, root and top together: top(root(x) U R').

``lgr_replay=stored`` replays the client's real latents of past tasks (kept at each task
end) instead of the generator's samples: an oracle that bounds what any generator can
reach. It stores data-derived features on the client and is not private in the paper's
sense; it never leaves the client either.

The generator, the labeller, the stored latents and the top never leave the client: with
scope ``root`` the upload is the root alone. Deviations from Algorithm 1 and from the
authors' code are listed in the README ("How FedLGR works here").
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from fedlgr.continual.batchnorm import eval_mode
from fedlgr.continual.fidelity import replay_fidelity
from fedlgr.federated.client import backward, optimizer_step
from fedlgr.federated.plugins import ClientPlugin, LocalContext
from fedlgr.models.generator import LatentVAE
from fedlgr.runtime import seeded_global_rng

SCHEDULES = ("two_phase", "joint")
REPLAYS = ("generator", "stored")


@torch.no_grad()
def latents_of(
    root: nn.Module, batches, max_batches: int | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The root's latents (eval mode) and the targets of one pass over ``batches``."""
    rs, ys = [], []
    with eval_mode(root):
        for step, (x, y) in enumerate(batches):
            if max_batches is not None and step >= max_batches:
                break
            if x.dim() == 4:
                x = x.contiguous(memory_format=torch.channels_last)
            rs.append(root(x).float())
            ys.append(y)
    return torch.cat(rs), torch.cat(ys)


class LatentReplay(ClientPlugin):
    name = "lgr"
    metric_names = ("fd_latent", "recon_mse", "fd_labels", "vae_epochs")

    def __init__(
        self,
        *,
        schedule: str = "two_phase",
        replay: str = "generator",
        hidden: int = 512,
        latent: int = 16,
        epochs: int = 300,
        batch_size: int = 32,
        lr: float = 1e-3,
        beta: float = 4.0,
        patience: int = 20,
        holdout: float = 0.2,
        lr_root: float = 1e-5,
        root_epochs: int | None = 1,
        replay_ratio: float = 4.0,
        sampler: str = "posterior",
        seed: int = 0,
    ):
        if schedule not in SCHEDULES or replay not in REPLAYS:
            raise ValueError(f"schedule {schedule!r} / replay {replay!r}")
        self.schedule, self.replay = schedule, replay
        self.hidden, self.latent, self.batch_size = hidden, latent, batch_size
        self.vae_epochs = epochs
        self.lr, self.beta, self.patience, self.holdout = lr, beta, patience, holdout
        self.lr_root, self.root_epochs, self.replay_ratio = lr_root, root_epochs, replay_ratio
        self.sampler = sampler  # prior: codes from N(0, I) | posterior: a Gaussian fitted to them
        self.generator_rng = torch.Generator().manual_seed(seed)
        self.generator: LatentVAE | None = None
        self.memory: torch.Tensor | None = None  # stored replay: past tasks' real latents
        self.labeller: nn.Module | None = None  # the top before this task's updates
        self.tasks_learnt = 0
        self.history: list[float] = []  # the generator's training loss per epoch, last fit
        self.fidelity: dict[str, float] = {}  # the last task end's figures
        self._heldout: torch.Tensor | None = None  # real latents the generator did not see
        self._current: torch.Tensor | None = None  # the last task's latents, at its end
        self._labeller_state: dict | None = None  # a restored labeller, until a top is at hand

    @property
    def replaying(self) -> bool:
        return self.tasks_learnt > 0

    # ------------------------------------------------------------------ replay

    @torch.no_grad()
    def replayed_latents(self, n: int) -> torch.Tensor:
        if self.replay == "stored":
            pick = torch.randint(len(self.memory), (n,), generator=self.generator_rng)
            return self.memory[pick.to(self.memory.device)]
        return self.generator.sample(n, self.generator_rng)

    @torch.no_grad()
    def pseudo_samples(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``n`` pseudo-latents R' and their labels T' from the pre-update top."""
        latents = self.replayed_latents(n)
        return latents, self.labeller(latents).float()

    def _union(self, top: nn.Module, r: torch.Tensor, y: torch.Tensor):
        """top(R U R') and (y U T'): one batch through the top."""
        n = round(len(r) * self.replay_ratio)
        if n == 0:
            return top(r), y
        latents, labels = self.pseudo_samples(n)
        return top(torch.cat([r, latents.to(r.dtype)])), torch.cat([y, labels.to(y.dtype)])

    # ------------------------------------------------------------------ hooks

    def on_task_start(self, ctx: LocalContext) -> None:
        if self.replaying:
            self.labeller = copy.deepcopy(ctx.model.top).eval().requires_grad_(False)

    def on_round_start(self, ctx: LocalContext) -> None:
        if not self.replaying:
            return
        if self.labeller is None and self._labeller_state is not None:  # restored mid-task
            self.labeller = copy.deepcopy(ctx.model.top).eval().requires_grad_(False)
            self.labeller.load_state_dict(self._labeller_state)
            self._labeller_state = None
        # Every round (a fresh optimiser, train.reset_optimizer=true, starts at train.lr_root).
        for group in ctx.optimizer.param_groups:
            if group.get("name") == "root":
                group["lr"] = self.lr_root
        if self.schedule == "two_phase":
            self._train_top(ctx)
            ctx.model.top.eval().requires_grad_(False)  # phase 2: the root alone

    def _train_top(self, ctx: LocalContext) -> None:
        """Phase 1: the top alone on the round's cached latents, with pseudo-samples."""
        latents, targets = latents_of(ctx.model.root, ctx.batches, ctx.max_batches)
        top, optimizer, size = ctx.model.top, ctx.optimizer, ctx.batches.batch_size
        top.train()
        for _ in range(ctx.epochs):
            order = torch.randperm(len(latents), generator=self.generator_rng)
            for i in range(0, len(latents), size):
                pick = order[i : i + size].to(latents.device)
                r, y = latents[pick], targets[pick]
                with ctx.autocast():
                    outputs, union = self._union(top, r, y)
                if len(union) < 2:
                    continue
                loss = nn.functional.mse_loss(outputs.float(), union)
                optimizer.zero_grad(set_to_none=True)
                backward(loss, ctx.scaler, optimizer)
                optimizer_step(optimizer, ctx.scaler)
                ctx.trained_samples += len(r)
                ctx.trained_loss += float(
                    nn.functional.mse_loss(outputs[: len(r)].detach(), y)
                ) * len(r)

    def epochs(self, ctx: LocalContext, epochs: int) -> int | None:
        if not self.replaying or self.schedule != "two_phase":
            return None
        if self.lr_root == 0:
            return 0  # the root would not move: phase 2 is skipped
        return self.root_epochs

    def forward(self, ctx: LocalContext, x: torch.Tensor, y: torch.Tensor):
        if not self.replaying or self.schedule != "joint":
            return None
        return self._union(ctx.model.top, ctx.model.root(x), y)

    def on_round_end(self, ctx: LocalContext) -> None:
        if self.replaying and self.schedule == "two_phase":  # the top as the round found it
            ctx.model.top.requires_grad_(True).train(ctx.model.training)

    def on_task_end(self, ctx: LocalContext) -> None:
        current = latents_of(ctx.model.root, ctx.plain_batches())[0]
        heldout = None
        if self.replay == "stored":
            parts = [current] if self.memory is None else [self.memory, current]
            self.memory = torch.cat(parts)
        else:
            heldout = self._fit_generator(current)
        self.tasks_learnt += 1
        self.labeller = None
        self._heldout, self._current = heldout, current

    def _fit_generator(self, current: torch.Tensor) -> torch.Tensor:
        """Train the generator on R (and R' of past tasks); its held-out real latents."""
        order = torch.randperm(len(current), generator=self.generator_rng).to(current.device)
        n_held = int(len(current) * self.holdout) if len(current) >= 10 else 0
        held, train = current[order[:n_held]], current[order[n_held:]]
        if self.generator is None:
            # Initialised from this client's own generator, not the process's global RNG:
            # the numbers must not depend on which other clients share the process.
            seed = int(torch.randint(2**62, (1,), generator=self.generator_rng))
            with seeded_global_rng(seed):
                self.generator = LatentVAE(
                    current.shape[1], self.hidden, self.latent, self.lr, self.beta
                ).to(current.device)
        else:  # R U R': as many pseudo-latents per past task as the task has scenes
            past = self.generator.sample(len(current) * self.tasks_learnt, self.generator_rng)
            cut = len(held) * self.tasks_learnt
            train = torch.cat([train, past[cut:]])
            held = torch.cat([held, past[:cut]])
        with torch.enable_grad():
            report = self.generator.fit(
                train, self.vae_epochs, self.batch_size, self.generator_rng, held, self.patience
            )
        if self.sampler == "posterior":
            self.generator.fit_code_density(train)
        self.history = report.train
        self.fit_report = report
        return held[:n_held]

    def task_metrics(self, ctx: LocalContext) -> dict[str, float]:
        """Replay fidelity against the real latents of every task seen so far."""
        heldout = self._heldout
        past = [latents_of(ctx.model.root, ctx.plain_batches(batches=b))[0] for b in ctx.seen[:-1]]
        real = torch.cat([*past, self._current])  # the current task's: from on_task_end
        top = ctx.model.top
        with eval_mode(top):
            self.fidelity = replay_fidelity(
                real,
                # Stored replay: the memory itself, not a resample (which alone adds a
                # finite-sample distance); the generator: as many samples as real latents.
                # (drawn with a fixed generator: measuring must not change the training).
                self.memory
                if self.replay == "stored"
                else self.generator.sample(len(real), torch.Generator().manual_seed(0)),
                top,
                heldout,
                None if self.generator is None else self.generator.reconstruct,
            )
        report = getattr(self, "fit_report", None)
        if self.generator is not None and report is not None:
            self.fidelity["vae_epochs"] = float(report.best_epoch)
        return dict(self.fidelity)

    # ------------------------------------------------------------------ state

    def state_dict(self) -> dict:
        return {
            "generator": None if self.generator is None else self.generator.state_dict(),
            "labeller": self._labeller_state
            if self.labeller is None
            else self.labeller.state_dict(),
            "memory": self.memory,
            "tasks_learnt": self.tasks_learnt,
            "rng": self.generator_rng.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()``'s figures (onto the device its tensors are on)."""
        if state.get("generator") is None:
            self.generator = None
        else:
            if self.generator is None:
                shift = state["generator"]["shift"]
                self.generator = LatentVAE(
                    shift.shape[0], self.hidden, self.latent, self.lr, self.beta
                ).to(shift.device)
            self.generator.load_state_dict(state["generator"])
        self.labeller, self._labeller_state = None, state.get("labeller")
        self.memory = state.get("memory")
        self.tasks_learnt = state.get("tasks_learnt", 0)
        if "rng" in state:
            self.generator_rng.set_state(state["rng"])
