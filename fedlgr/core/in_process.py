"""The in-process runtime, on Lightning Fabric: both sides of a round in our processes.

:class:`Orchestrator` is a runtime's rounds (:class:`fedlgr.core.rounds.Rounds`; Fabric's
set-up and launch: :mod:`fedlgr.shell.run.experiment`). In each round every client the
strategy chose trains its local model for E epochs on its shard of the current task, uploads the
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
trains its own, every process keeps a copy of the server side, which aggregates over them
all (:class:`FabricCollective`: one weighted ``all_reduce``); per-client rows are summed
likewise, and rank 0 alone logs. Seeds are per client, so both modes compute the same numbers.
"""

from __future__ import annotations

import dataclasses
import io
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
import torch.distributed as dist

from fedlgr.core.client.side import ClientSide
from fedlgr.core.evaluation import scored_clients
from fedlgr.core.faults import Faults
from fedlgr.core.messages import EvaluateIns, EvaluateRes, RoundPlan, TrainRes, nbytes
from fedlgr.core.records import RoundLog
from fedlgr.core.rounds import EpochProgress
from fedlgr.core.server.evaluate import ServerEvaluation, serve_round
from fedlgr.core.server.side import Collective, ServerSide
from fedlgr.core.state import rng_states, set_rng_states, to_device

if TYPE_CHECKING:
    from fedlgr.core.client.pool import Resolved
    from fedlgr.core.data.scenes import FederatedSplit, Scenes
    from fedlgr.core.settings import ExperimentConfig


class Orchestrator:
    def __init__(
        self,
        fabric,
        config: ExperimentConfig,
        scenes: Scenes,
        split: FederatedSplit,
        spill: Path | None = None,
        resolved: Resolved | None = None,
    ):
        self.fabric, self.config = fabric, config
        self.device = fabric.device
        self.rank, self.world = fabric.global_rank, fabric.world_size
        self.server = ServerSide(config).to(self.device)
        self.collective = FabricCollective(fabric)
        mine = [s.client for s in split.clients if s.client % self.world == self.rank]
        self.indices = set(mine)
        self.client_side = ClientSide(
            config, scenes, split, mine, self.device, fabric.autocast, spill, resolved
        )
        self.scored = scored_clients(config)  # federated.evaluate, eval_every
        self.faults = Faults(config.federated.faults, config.data.clients, config.seed)
        # federated.server_eval: rank 0, which logs, scores the global model.
        self.server_eval = (
            ServerEvaluation(config, self.client_side.test)
            if config.federated.server_evaluates and self.rank == 0
            else None
        )

    def aggregate(self, trained: list[TrainRes], task: int = 0) -> None:
        """:meth:`ServerSide.aggregate` over every process's uploads, held to their scenes."""
        side = self.client_side
        capacity = {
            r.client: side.n_samples(r.client, task) for r in trained if r.client in side.shards
        }
        self.server.aggregate(trained, capacity, collective=self.collective)

    @property
    def clients(self):
        """This process's clients that are whole now (all of them with whole idle clients,
        ``runtime.idle_clients=live``)."""
        return self.client_side.clients

    @property
    def local_clients(self) -> int:
        """The clients that train in this process (with ``runtime.devices=N``, its share)."""
        return len(self.indices)

    def close(self) -> None:
        """Let go of the idle clients' files."""
        self.client_side.close()

    def run_round(self, plan: RoundPlan, progress: EpochProgress | None = None) -> RoundLog:
        """One round of ``plan``: the clients the strategy chose train, the server
        aggregates, every client evaluates the new global tensors. ``progress(client,
        epoch)`` after each local epoch of this process's clients."""
        start = time.perf_counter()
        round_, task = plan.round, plan.task
        chosen = self.server.chosen(plan)
        faults = self.faults.what(round_, chosen)  # simulated: client -> what failed
        chosen = [c for c in chosen if faults.get(c) != "dropped"]
        # Our clients start from the initial model and keep every download: they always
        # hold the global tensors (round 1's initial ones are billed in ``bytes_down``).
        ins = {c: self.server.train_ins(plan, c) for c in chosen if c in self.indices}
        shared = self.server.global_weights  # what they started from
        trained = {
            t.client: self.faults.sent(t, shared, round_)
            for t in self.client_side.train(ins, progress)
        }
        # a late upload comes after the round's deadline: it is dropped, as on Flower
        on_time = [t for c, t in trained.items() if not faults.get(c, "").endswith("late")]
        # The server's work - aggregation, its update, its evaluation - is its own cost,
        # never a client's.
        served = serve_round(
            self.server, self.server_eval, plan, lambda: self.aggregate(on_time, task)
        )
        scored = self.scored(plan, chosen)
        ins_eval = EvaluateIns(plan, self.server.global_weights, scored)
        evaluated = {e.client: e for e in self.client_side.evaluate(ins_eval)}
        rows = {}
        for c in sorted(self.indices):  # a client with no figures has a row of NaN
            t, e = trained.get(c), evaluated.get(c)
            if t is None and e is None:
                rows[c] = {}
            elif t is None:
                rows[c] = self.server.row(None, e, 0, self.server.bytes_down(round_, False))
            else:  # a chosen client moves its payloads too
                up = nbytes(t.weights) + nbytes(t.payload)
                # not scoring: it fetched only the global tensors it trained from
                down = self.server.bytes_down(round_) if e else self.server.initial_bytes
                down += nbytes(ins[c].payload)
                rows[c] = self.server.row(t, e or EvaluateRes(c), up, down)
        # Rows of other processes are zero here: the sum over processes fills them in.
        table = torch.from_numpy(self.server.table(rows, fill=0.0)).to(self.device)
        table = self.collective.all_reduce_sum(table).cpu().numpy()
        seconds = time.perf_counter() - start
        return self.server.round_log(
            plan,
            table,
            seconds,
            participants=chosen,
            served=served,
            faults=faults,
            byzantine=self.faults.byzantine,
        )

    # ------------------------------------------------------------------ state

    def state_dict(self) -> dict:
        """The run's state after a round, whole in rank 0 (every process calls this: its
        clients' states and random generators are gathered there): the server's (global
        tensors, strategy state; the same in every process), every client's, and each
        process's random generators. Other processes get an empty dict."""
        part = {
            "clients": to_device(self.client_side.state_dict(), CPU),
            "rng": rng_states(),
        }
        parts = _gather(self.fabric, part)
        if parts is None:
            return {}
        return {
            "server": to_device(self.server.state_dict(), CPU),
            "clients": {i: c for p in parts for i, c in p["clients"].items()},
            "rng": [p["rng"] for p in parts],  # per process
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore a checkpoint's server state, this process's clients (``state`` holds
        every client of every process) and this process's random generators."""
        self.server.load_state_dict(state["server"], self.device)
        mine = {i: s for i, s in state["clients"].items() if i in self.indices}
        self.client_side.load_state_dict(mine, self.server.global_weights)
        set_rng_states(state["rng"][self.rank])


CPU = torch.device("cpu")


@dataclasses.dataclass
class FabricCollective(Collective):
    """Fabric's processes (a :class:`Collective`): objects by torch.distributed's object
    gather, as bytes that ``torch.load`` puts on this process's device (a tensor of another
    GPU would come back there); sums by ``all_reduce``."""

    fabric: Any

    @property
    def processes(self) -> int:
        return self.fabric.world_size

    def all_gather(self, part: Any) -> list[Any]:
        if self.fabric.world_size == 1:
            return [part]
        buffer, parts = io.BytesIO(), [None] * self.fabric.world_size
        torch.save(part, buffer)
        dist.all_gather_object(parts, buffer.getvalue())
        device = self.fabric.device
        return [torch.load(io.BytesIO(p), map_location=device, weights_only=False) for p in parts]

    def all_reduce_sum(self, flat: torch.Tensor) -> torch.Tensor:
        if self.fabric.world_size == 1:
            return flat
        return self.fabric.all_reduce(flat, reduce_op="sum")


def _gather(fabric, part: dict) -> list[dict] | None:
    """Every process's ``part`` on rank 0 (None elsewhere). Fabric's collectives move
    tensors only; client states are nested dicts, hence torch.distributed's object
    gather (gloo on CPU, the backend Fabric set up otherwise)."""
    if fabric.world_size == 1:
        return [part]
    parts = [None] * fabric.world_size if fabric.global_rank == 0 else None
    dist.gather_object(part, parts, dst=0)
    return parts
