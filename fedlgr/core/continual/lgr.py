"""FedLGR's client side: latent generative replay (the paper's Algorithm 1).

FedLGR = FedRoot aggregation (scope ``root``) + this plug-in on every client. In Task 1 the
client trains as FedRoot does. At the end of every task its generator (a VAE over root
latents, ``fedlgr.core.models.generator``) learns the latents R of the task's scenes,
together with as many pseudo-latents R' per past task from the generator as it was. In
every round of a later task:

1. the root trains at ``continual.lgr.lr_root`` (lr_R), the top at ``train.lr_top``, and -
   with ``continual.lgr.freeze_root_bn`` (``fedlgr.core.continual.batchnorm``) - the
   root's BatchNorm statistics stay as they were after Task 1, so the latent space the
   generator learnt stays put;
2. ``continual.lgr.replay_ratio`` pseudo-latents R' per real sample are drawn and labelled
   T' = top(R') by the top *as it was when the task began* (a frozen copy, eval mode);
3. the top trains on <R, y> U <R', T'> **as one batch**: its BatchNorm sees the union;
   the root learns from the current data only. ``continual.lgr.schedule`` says how:

   * ``two_phase`` (the authors' code): first the top alone, for ``train.epochs`` epochs
     over the current scenes' latents - computed once per round, root in eval mode, one
     pass of the client's batches (augmented if augmentation is on) - each batch with its
     pseudo-samples; then the root alone, at lr_R on the current data with the top frozen
     (eval mode, no gradients), for ``continual.lgr.root_epochs`` epochs (default 1;
     ``None``: ``train.epochs`` as in the authors' code; none when lr_R is 0);
   * ``joint``: one pass per batch, root and top together: top(root(x) U R').

Keeping the replayed latents valid while the root learns (``fedlgr.core.continual.drift``;
all off is the paper's method). From the second task on:

* ``continual.lgr.drift=compensate``: at every round start an affine map from the latents
  of the current scenes under the root as the task found it (a frozen copy, kept at the
  task's start) to their latents under the root now - after local training and
  aggregation - is fitted (ridge ``continual.lgr.compensate_ridge``, shrunk towards the
  identity) and applied to every replayed latent before the top sees it; the labeller
  still labels the old latent. At a task's end the stored latents (and the generator's
  past samples, before it is refitted) are carried into the current space with it.
* ``continual.lgr.drift=distill``: the root's loss gets ``continual.lgr.distill_weight`` x
  the mean squared difference between its latents of the batch and those of the frozen
  task-start copy (feature distillation, Liu et al. CVPRW 2020): 0 at the task's start.
* ``compensate+distill``: both.
* ``continual.lgr.train_blocks=k``: only the root's last k blocks train
  (``Root.blocks()``); the others keep their weights and their BatchNorm statistics (eval
  mode). FedRoot still averages the whole root (the frozen blocks, equal on every client,
  average to themselves).

``continual.lgr.replay=stored`` replays the client's real latents of past tasks (kept at
each task end) instead of the generator's samples: an oracle that bounds what any
generator can reach. It stores data-derived features on the client and is not private in
the paper's sense; it never leaves the client either.

The generator, the labeller, the stored latents and the top never leave the client: with
scope ``root`` the upload is the root alone. Deviations from Algorithm 1 and from the
authors' code are listed in docs/fedlgr.md ("How FedLGR works here").
"""

from __future__ import annotations

import copy
import dataclasses

import torch
from torch import nn

from fedlgr.core.client.plugins import ClientPlugin, LocalContext
from fedlgr.core.client.training import backward, optimizer_step
from fedlgr.core.continual.batchnorm import eval_mode, freeze_batchnorm_statistics
from fedlgr.core.continual.drift import DriftMap, drift_distance, fit_drift_map
from fedlgr.core.continual.fidelity import replay_fidelity
from fedlgr.core.methods import LGRSettings
from fedlgr.core.models.generator import LatentVAE
from fedlgr.core.state import seeded_global_rng


@torch.no_grad()
def latents_of(
    root: nn.Module, batches, max_batches: int | None = None, block: int | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The root's latents (eval mode) and the targets of one pass over ``batches``; with
    ``block``, the activations entering that block instead, flattened per scene."""
    rs, ys = [], []
    with eval_mode(root):
        for step, (x, y) in enumerate(batches):
            if max_batches is not None and step >= max_batches:
                break
            if x.dim() == 4:
                x = x.contiguous(memory_format=torch.channels_last)
            r = root(x) if block is None else root.forward_to(x, block).flatten(1)
            rs.append(r.float())
            ys.append(y)
    return torch.cat(rs), torch.cat(ys)


class LatentReplay(ClientPlugin):
    name = "lgr"
    # Task ends: the replay's fidelity. Every round of a later task: the latent drift.
    metric_names = (
        "fd_latent",
        "recon_mse",
        "fd_labels",
        "vae_epochs",
        "drift",
        "drift_residual",
        "drift_past",
        "drift_past_residual",
    )

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
        drift: str = "none",
        compensate_ridge: float = 1.0,
        distill_weight: float = 1.0,
        train_blocks: int | None = None,
        replay_layer: str = "latent",
        seed: int = 0,
    ):
        self.replay_layer = replay_layer
        self.schedule, self.replay = schedule, replay
        self.compensate, self.distill = "compensate" in drift, "distill" in drift
        self.compensate_ridge, self.distill_weight = compensate_ridge, distill_weight
        self.train_blocks = train_blocks  # None: the whole root trains
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
        # The root as the current task found it (frozen, eval mode), for compensation,
        # distillation and the drift figures; its latents of the current scenes.
        self.root_start: nn.Module | None = None
        self._root_start_state: dict | None = None  # restored, until a root is at hand
        self._start_latents: torch.Tensor | None = None
        self._past_start: torch.Tensor | None = None  # diagnostics: past scenes, task start
        self.drift_map: DriftMap | None = None  # fitted at this round's start
        self._frozen: list[nn.Module] = []  # blocks kept as they are this round
        self._latents: torch.Tensor | None = None  # the root's latents of the batch (distill)
        self._shape: tuple[int, ...] | None = None  # freeze: one scene's replayed activations

    @classmethod
    def from_settings(cls, settings: LGRSettings, continual, seed: int) -> LatentReplay:
        kept = {f.name: getattr(settings, f.name) for f in dataclasses.fields(settings)}
        del kept["freeze_root_bn"]  # FrozenRootStatistics' (fedlgr.core.continual)
        return cls(**kept, seed=seed)

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
        """``n`` pseudo-latents R' and their labels T' from the pre-update top (at the freeze
        point: from the task-start root's blocks above it and the pre-update top)."""
        latents = self.replayed_latents(n)
        if self.replay_layer == "latent":
            return latents, self.labeller(latents).float()
        point = self.freeze_point(self.root_start)
        above = self.root_start.forward_from(self.unflatten(latents), point)
        return latents, self.labeller(above).float()

    def freeze_point(self, root: nn.Module) -> int | None:
        """Replay at the freeze point: the index of ``root``'s first trained block."""
        if self.replay_layer != "freeze":
            return None
        return max(len(root.blocks()) - self.train_blocks, 0)

    def unflatten(self, z: torch.Tensor) -> torch.Tensor:
        """Flat replayed activations as the blocks above the freeze point take them."""
        z = z.reshape(len(z), *self._shape)
        return z.contiguous(memory_format=torch.channels_last) if z.dim() == 4 else z

    def replay_latents(self, root: nn.Module, batches) -> torch.Tensor:
        """What is replayed of ``batches``' scenes: the root's latents, or (freeze point)
        the flattened activations entering the first trained block."""
        if self.replay_layer == "latent":
            return latents_of(root, batches)[0]
        point = self.freeze_point(root)
        if self._shape is None:
            x, _ = next(iter(batches))
            if x.dim() == 4:
                x = x.contiguous(memory_format=torch.channels_last)
            with torch.no_grad(), eval_mode(root):
                self._shape = tuple(root.forward_to(x[:1], point).shape[1:])
        return latents_of(root, batches, block=point)[0]

    def _freeze_point_union(self, ctx: LocalContext, x: torch.Tensor, y: torch.Tensor):
        """top(root above the freeze point(Z U Z')) and (y U T'): the frozen blocks run
        once, without gradients; the trained blocks and the top see real and replayed
        activations as one batch."""
        root = ctx.model.root
        point = self.freeze_point(root)
        with torch.no_grad():
            z = root.forward_to(x, point)
        n = round(len(x) * self.replay_ratio)
        if n:
            latents, labels = self.pseudo_samples(n)
            z = torch.cat([z, self.unflatten(latents).to(z.dtype)])
            y = torch.cat([y, labels.to(y.dtype)])
        r = root.forward_from(z, point)
        self._latents = r[: len(x)]
        return ctx.model.top(r), y

    def _union(self, top: nn.Module, r: torch.Tensor, y: torch.Tensor):
        """top(R U map(R')) and (y U T'): one batch through the top (map: the drift
        compensation, where on; T' is labelled on the unmapped R')."""
        n = round(len(r) * self.replay_ratio)
        if n == 0:
            return top(r), y
        latents, labels = self.pseudo_samples(n)
        if self.drift_map is not None:
            latents = self.drift_map(latents)
        return top(torch.cat([r, latents.to(r.dtype)])), torch.cat([y, labels.to(y.dtype)])

    # ------------------------------------------------------------------ hooks

    def on_task_start(self, ctx: LocalContext) -> None:
        if self.replaying:
            self.labeller = copy.deepcopy(ctx.model.top).eval().requires_grad_(False)
            self.root_start = copy.deepcopy(ctx.model.root).eval().requires_grad_(False)
            self._start_latents = self._past_start = None

    def _restore(self, ctx: LocalContext) -> None:
        """The labeller and the task-start root from a checkpoint, once a model is at hand."""
        if self.labeller is None and self._labeller_state is not None:  # restored mid-task
            self.labeller = copy.deepcopy(ctx.model.top).eval().requires_grad_(False)
            self.labeller.load_state_dict(self._labeller_state)
            self._labeller_state = None
        if self.root_start is None and self._root_start_state is not None:
            self.root_start = copy.deepcopy(ctx.model.root).eval().requires_grad_(False)
            self.root_start.load_state_dict(self._root_start_state)
            self._root_start_state = None

    def start_latents(self, ctx: LocalContext) -> torch.Tensor:
        """The task-start root's latents of the current scenes (once per task)."""
        if self._start_latents is None:
            self._start_latents = latents_of(self.root_start, ctx.plain_batches())[0]
        return self._start_latents

    def fit_map(self, ctx: LocalContext) -> DriftMap:
        """The drift map from the task-start root's latents of the current scenes to the
        current root's."""
        now = latents_of(ctx.model.root, ctx.plain_batches())[0]
        return fit_drift_map(self.start_latents(ctx), now, self.compensate_ridge)

    def on_round_start(self, ctx: LocalContext) -> None:
        if not self.replaying:
            return
        self._restore(ctx)
        # Every round (a fresh optimiser, train.reset_optimizer=true, starts at train.lr_root).
        for group in ctx.optimizer.param_groups:
            if group.get("name") == "root":
                group["lr"] = self.lr_root
        self._freeze_blocks(ctx.model.root)
        self.drift_map = self.fit_map(ctx) if self.compensate else None
        if self.schedule == "two_phase":
            self._train_top(ctx)
            ctx.model.top.eval().requires_grad_(False)  # phase 2: the root alone

    def _freeze_blocks(self, root: nn.Module) -> None:
        """``train_blocks``: every block below the last k keeps its weights (no gradients:
        Adam skips them) and its BatchNorm statistics (eval mode) this round."""
        self._frozen = []
        if self.train_blocks is None:
            return
        blocks = root.blocks()
        self._frozen = blocks[: max(len(blocks) - self.train_blocks, 0)]
        for block in self._frozen:
            block.requires_grad_(False)
            freeze_batchnorm_statistics(block)

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
        if not self.replaying:
            return None
        if self.replay_layer == "freeze":
            return self._freeze_point_union(ctx, x, y)
        if self.schedule == "joint":
            r = ctx.model.root(x)
            self._latents = r
            return self._union(ctx.model.top, r, y)
        if not self.distill:
            return None
        r = self._latents = ctx.model.root(x)  # phase 2: the root alone (kept for the loss)
        return ctx.model.top(r), y

    def loss(self, ctx, x, y, outputs, loss):
        if not (self.replaying and self.distill) or self._latents is None:
            return loss
        return loss + self.distill_weight * self.distillation(self._latents, x)

    def distillation(self, latents: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """The mean squared difference between ``latents`` (the root's, of batch ``x``) and
        the task-start root's latents of ``x`` (no gradient through those)."""
        with torch.no_grad():
            target = self.root_start(x).float()
        self._latents = None
        return nn.functional.mse_loss(latents.float(), target)

    def on_round_end(self, ctx: LocalContext) -> None:
        if self.replaying and self.schedule == "two_phase":  # the top as the round found it
            ctx.model.top.requires_grad_(True).train(ctx.model.training)
        for block in self._frozen:
            block.requires_grad_(True)
        self._frozen, self._latents = [], None

    def on_task_end(self, ctx: LocalContext) -> None:
        current = self.replay_latents(ctx.model.root, ctx.plain_batches())
        # Compensation: what is kept of past tasks moves into the space of the root as the
        # task leaves it (the next task's start), with the map fitted on this task's scenes.
        carry = None
        if self.compensate and self.replaying and self.root_start is not None:
            carry = fit_drift_map(self.start_latents(ctx), current, self.compensate_ridge)
        heldout = None
        if self.replay == "stored":
            memory = self.memory if carry is None or self.memory is None else carry(self.memory)
            self.memory = current if memory is None else torch.cat([memory, current])
        else:
            heldout = self._fit_generator(current, carry)
        self.tasks_learnt += 1
        self.labeller = self.root_start = self.drift_map = None
        self._start_latents = self._past_start = None
        self._heldout, self._current = heldout, current

    def _fit_generator(self, current: torch.Tensor, carry: DriftMap | None = None) -> torch.Tensor:
        """Train the generator on R (and R' of past tasks, carried into the current space by
        ``carry`` where given); its held-out real latents."""
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
            if carry is not None:
                past = carry(past)
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
        root = ctx.model.root
        past = [self.replay_latents(root, ctx.plain_batches(batches=b)) for b in ctx.seen[:-1]]
        real = torch.cat([*past, self._current])  # the current task's: from on_task_end
        top, point = ctx.model.top, self.freeze_point(root)
        if point is not None:  # the labeller's view: the blocks above the point, the top
            top = nn.Sequential(_Above(root, point, self.unflatten), top)
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

    @torch.no_grad()
    def round_metrics(self, ctx: LocalContext) -> dict[str, float]:
        """The latent drift after a round of a later task (aggregation included), before
        any task end: ``drift``, the distance between the current root's latents of the
        current scenes and their latents at the task's start (what a client can compute);
        ``drift_residual``, the same after the compensation map fitted now (compensate
        only); ``drift_past`` / ``drift_past_residual``: the same on the past tasks' scenes
        (the true drift, from scenes a client on a real deployment would no longer hold:
        read for the measurement only)."""
        if not self.replaying:
            return {}
        self._restore(ctx)
        if self.root_start is None:
            return {}
        then = self.start_latents(ctx)
        now = latents_of(ctx.model.root, ctx.plain_batches())[0]
        out = {"drift": drift_distance(now, then)}
        mapping = fit_drift_map(then, now, self.compensate_ridge) if self.compensate else None
        if mapping is not None:
            out["drift_residual"] = drift_distance(now, mapping(then))
        if len(ctx.seen) > 1:
            past = [ctx.plain_batches(batches=b) for b in ctx.seen[:-1]]
            if self._past_start is None:
                self._past_start = torch.cat([latents_of(self.root_start, b)[0] for b in past])
            past_now = torch.cat([latents_of(ctx.model.root, b)[0] for b in past])
            out["drift_past"] = drift_distance(past_now, self._past_start)
            if mapping is not None:
                out["drift_past_residual"] = drift_distance(past_now, mapping(self._past_start))
        return out

    # ------------------------------------------------------------------ state

    def state_dict(self) -> dict:
        return {
            "generator": None if self.generator is None else self.generator.state_dict(),
            "labeller": self._labeller_state
            if self.labeller is None
            else self.labeller.state_dict(),
            "memory": self.memory,
            "root_start": self._root_start_state
            if self.root_start is None
            else self.root_start.state_dict(),
            "tasks_learnt": self.tasks_learnt,
            "shape": self._shape,
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
        self.root_start, self._root_start_state = None, state.get("root_start")
        self._start_latents = self._past_start = self.drift_map = None
        self.tasks_learnt = state.get("tasks_learnt", 0)
        self._shape = None if state.get("shape") is None else tuple(state["shape"])
        if "rng" in state:
            self.generator_rng.set_state(state["rng"])


class _Above(nn.Module):
    """The root's blocks from ``point`` on, over flat replayed activations."""

    def __init__(self, root: nn.Module, point: int, unflatten):
        super().__init__()
        self.root, self.point, self.unflatten = root, point, unflatten

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.root.forward_from(self.unflatten(z), self.point)
