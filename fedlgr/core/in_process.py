"""The Fabric-based federated round orchestrator (SPEC 4.3): both sides in our processes.

:class:`Orchestrator` runs the round loop's rounds (a :class:`fedlgr.shell.run.loop.Rounds`;
Fabric's set-up and launch: :mod:`fedlgr.shell.run.experiment`). In each round every
client trains its local model for E epochs on its shard of the current task, uploads the
tensors its strategy and scope share, the server aggregates (sample-weighted mean, then the
strategy's server update), every client downloads the new global tensors, at a task's last
round ends the task (importance, memories, generators: plugins' ``on_task_end``), and
evaluates its own model on the shared test set - the scenes of every task seen so far, and
each task's scenes on their own. The two sides meet only through
:mod:`fedlgr.core.messages` (:class:`ServerSide`, :class:`ClientSide`); the Flower
runtime (``fedlgr.shell.deploy.flower``) puts the same two sides on different machines.

Plain FL is a schedule of one task, "all", of ``federated.rounds`` rounds. By default all
clients run in one process on one device. With ``runtime.devices=N`` (and
``runtime.num_nodes``) the clients are dealt round-robin to the processes, each process
trains its own, every process keeps a copy of the server side, and aggregation is one
weighted ``all_reduce``; per-client rows are reduced to rank 0, which alone logs. Seeds
are per client, so both modes compute the same numbers.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from fedlgr.core.client.side import ClientSide
from fedlgr.core.messages import EvaluateIns, RoundPlan, TrainRes, nbytes
from fedlgr.core.records import RoundLog
from fedlgr.core.server.evaluate import ServerEvaluation, serve_round
from fedlgr.core.server.side import ServerSide
from fedlgr.shell.config import ExperimentConfig
from fedlgr.shell.data.dataset import Scenes
from fedlgr.shell.data.splits import FederatedSplit
from fedlgr.shell.run.checkpoint import to_device
from fedlgr.shell.run.loop import EpochProgress


class Orchestrator:
    def __init__(self, fabric, config: ExperimentConfig, scenes: Scenes, split: FederatedSplit):
        self.fabric, self.config = fabric, config
        self.device = fabric.device
        self.rank, self.world = fabric.global_rank, fabric.world_size
        self.server = ServerSide(config).to(self.device)
        mine = [s.client for s in split.clients if s.client % self.world == self.rank]
        self.client_side = ClientSide(config, scenes, split, mine, self.device, fabric.autocast)
        self.clients = self.client_side.clients
        self.fields = self.server.fields
        # federated.server_eval: rank 0, which logs, scores the global model.
        self.server_eval = (
            ServerEvaluation(config, self.client_side.test)
            if config.federated.server_evaluates and self.rank == 0
            else None
        )

    def aggregate(self, trained: list[TrainRes]) -> None:
        """Sample-weighted mean over all clients of all processes, then the server update."""
        sums, total = self.server.sums(trained)
        if self.world > 1:
            # One collective for everything: the flattened sums and the sample count.
            like = self.server.global_weights
            parts = [
                sums.get(k, torch.zeros_like(like[k], dtype=torch.float64)).flatten()
                for k in self.server.keys
            ]
            flat = torch.cat(
                [*parts, torch.tensor([total], dtype=torch.float64, device=self.device)]
            )
            flat = self.fabric.all_reduce(flat, reduce_op="sum")
            total, offset = float(flat[-1]), 0
            for k in self.server.keys:
                size = like[k].numel()
                sums[k] = flat[offset : offset + size].view_as(like[k])
                offset += size
        self.server.update(sums, total)

    @property
    def local_clients(self) -> int:
        """The clients that train in this process (with ``runtime.devices=N``, its share)."""
        return len(self.clients)

    def run_round(self, plan: RoundPlan, progress: EpochProgress | None = None) -> RoundLog:
        """One round of ``plan``: every client trains, the server aggregates, every client
        evaluates the new global tensors. ``progress(client, epoch)`` after each local epoch
        of this process's clients."""
        start = time.perf_counter()
        round_, task = plan.round, plan.task
        # Our clients start from the initial model and keep every download: they always
        # hold the global tensors (round 1's initial ones are billed in ``bytes_down``).
        trained = self.client_side.train(self.server.train_ins(plan), progress)
        # The server's work - aggregation, its update, its evaluation - is its own cost,
        # never a client's.
        server, initial = serve_round(
            self.server, self.server_eval, round_, task, lambda: self.aggregate(trained)
        )
        evaluated = self.client_side.evaluate(EvaluateIns(plan, self.server.global_weights))
        down = self.server.bytes_down(round_)
        rows = {
            t.client: self.server.row(t, e, nbytes(t.weights), down)
            for t, e in zip(trained, evaluated, strict=True)
        }
        # Rows of other processes are zero here: the sum over processes fills them in.
        table = self.server.table(rows, fill=0.0)
        if self.world > 1:
            table = self.fabric.all_reduce(table.to(self.device), reduce_op="sum").cpu()
        log = self.server.round_log(plan, table, time.perf_counter() - start)
        log.server, log.initial = server, initial
        return log

    # ------------------------------------------------------------------ checkpoints

    def save(
        self,
        folder: Path | None,
        rounds: list[RoundLog],
        run_id: str | None,
        elapsed: float,
        keep: int,
        digest: str = "",
    ) -> Path | None:
        """Checkpoint the run after its last round in ``rounds``: every process's clients,
        gathered to rank 0, which writes (:func:`fedlgr.shell.run.resume.save_checkpoint`)."""
        from fedlgr.shell.run.resume import save_checkpoint

        return save_checkpoint(self.fabric, folder, self, rounds, run_id, elapsed, keep, digest)

    def state_dict(self) -> dict:
        """This process's part of the run's state: the server's (global tensors, strategy
        state; the same in every process) and its own clients'."""
        return {"server": self.server.state_dict(), "clients": self.client_side.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """Restore a checkpoint's server state and this process's clients (``state`` holds
        every client of every process)."""
        self.server.load_state_dict(state["server"], self.device)
        self.client_side.load_state_dict(to_device(state["clients"], self.device))
