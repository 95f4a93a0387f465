"""The ServerApp: a fedlgr run whose clients are robots behind a Flower SuperLink.

``flwr run`` starts it on the SuperLink's machine with the app's run config: ``config``
(a fedlgr config file on that machine; empty: the defaults) and ``overrides``
(``key=value`` separated by spaces). It runs the schedule with the same round loop as
``fedlgr run`` (:func:`fedlgr.federated.experiment.drive`) - the same MLflow keys,
artifacts and summary, plus the tag ``runtime=flower`` - around :class:`FlowerRounds`,
which speaks to the robots with :mod:`fedlgr.deploy.flower.wire` messages and aggregates
with :class:`fedlgr.federated.server_side.ServerSide`, the very code of the in-process
runs.

Drop-outs: each exchange waits ``deploy.round_timeout_s`` at most; the round aggregates
the uploads that arrived if there are at least ``deploy.min_clients`` of them (default:
all clients), records the missing clients (NaN rows, ``round/missing_clients``, tag
``fedlgr.missing``), and a robot that comes back is sent the global tensors with its
next training message. Checkpoints and ``--resume`` are not available here yet: the
robots' state is on the robots.
"""

from __future__ import annotations

import functools
import shlex
import time

from flwr.app import Context, Message, RecordDict
from flwr.serverapp import Grid, ServerApp

from fedlgr.config import ExperimentConfig, load_config, to_yaml
from fedlgr.deploy.flower import wire
from fedlgr.errors import FedlgrError
from fedlgr.federated.messages import EvaluateIns, RoundPlan, TrainRes
from fedlgr.federated.rounds import RoundLog
from fedlgr.federated.server_side import ServerSide

app = ServerApp()
POLL_S = 0.2  # how often the server asks the SuperLink for replies


class FlowerRounds:
    """``run_round`` for :func:`drive`, with the clients on the robots."""

    clients = ()  # no client lives in this process

    def __init__(self, grid: Grid, config: ExperimentConfig, echo=print):
        self.grid, self.config, self.echo = grid, config, echo
        self.server = ServerSide(config)
        self.fields = self.server.fields
        self.config_yaml = to_yaml(config)
        self.holders: set[int] = set()  # nodes that hold the current global tensors
        self.min_clients = config.deploy.min_clients or config.data.clients
        self.joined = False

    def wait_for_robots(self) -> None:
        """Until every client's robot has joined, or ``deploy.join_timeout_s``."""
        want, deadline = (
            self.config.data.clients,
            time.monotonic() + self.config.deploy.join_timeout_s,
        )
        nodes: list[int] = []
        while time.monotonic() < deadline:
            nodes = list(self.grid.get_node_ids())
            if len(nodes) >= want:
                break
            time.sleep(1.0)
        if len(nodes) < self.min_clients:
            raise FedlgrError(
                f"{len(nodes)} of {want} robots joined within deploy.join_timeout_s="
                f"{self.config.deploy.join_timeout_s:g} (deploy.min_clients={self.min_clients})"
            )
        self.echo(f"{len(nodes)} robots joined (nodes {', '.join(map(str, sorted(nodes)))})")
        self.joined = True

    def exchange(self, kind: str, contents: dict[int, RecordDict], round_: int):
        """Send ``contents`` (node -> message content); the replies that came back in
        time, by node. Error replies (a robot's exception) are reported, not raised."""
        messages = [
            Message(content, dst_node_id=node, message_type=kind, group_id=str(round_))
            for node, content in contents.items()
        ]
        # Grid.send_and_receive polls every 3 s: up to 6 s idle per round for two
        # exchanges. The same push/pull with a 0.2 s poll.
        started = time.monotonic()
        pending = {i for i in self.grid.push_messages(messages) if i}
        replies = []
        deadline = time.monotonic() + self.config.deploy.round_timeout_s
        while pending and time.monotonic() < deadline:
            for reply in self.grid.pull_messages(list(pending)):
                pending.discard(reply.metadata.reply_to_message_id)
                replies.append(reply)
            if pending:
                time.sleep(POLL_S)
        seconds = time.monotonic() - started
        # An error reply may come from the SuperLink itself (a robot gone offline): the
        # robot is the one the message was sent to.
        to_node = {m.metadata.message_id: m.metadata.dst_node_id for m in messages}
        out = {}
        for reply in replies:
            node = to_node.get(reply.metadata.reply_to_message_id, reply.metadata.src_node_id)
            if reply.has_error():
                self.echo(f"round {round_}, {kind}: node {node} failed: {reply.error.reason}")
            else:
                out[node] = reply
        self.echo(
            f"round {round_}, {kind}: {len(out)} of {len(messages)} replies ({seconds:.1f} s)"
        )
        return out

    def run_round(
        self,
        round_: int,
        task: int = 0,
        first_of_task: bool = False,
        last_of_task: bool = False,
        progress=None,
    ) -> RoundLog:
        if not self.joined:
            self.wait_for_robots()
        start = time.perf_counter()
        plan = RoundPlan(round_, task, first_of_task, last_of_task)
        nodes = sorted(self.grid.get_node_ids())
        down: dict[int, int] = {}
        contents = {}
        for node in nodes:
            ins = self.server.train_ins(plan, holds_global=node in self.holders)
            contents[node] = wire.encode_train_ins(ins, self.config_yaml)
            down[node] = wire.payload_bytes(contents[node])
        trained: dict[int, tuple[int, TrainRes, int]] = {}  # client -> (node, upload, bytes)
        for node, reply in self.exchange("train", contents, round_).items():
            res = wire.decode_train_res(reply.content)
            if res.client in trained:
                self.echo(
                    f"round {round_}: nodes {trained[res.client][0]} and {node} both "
                    f"serve client {res.client}; node {node}'s upload is ignored"
                )
                continue
            trained[res.client] = (node, res, wire.payload_bytes(reply.content))
        self.holders = set()
        if len(trained) < self.min_clients:
            raise FedlgrError(
                f"round {round_}: {len(trained)} of {self.config.data.clients} robots sent "
                f"their update within deploy.round_timeout_s={self.config.deploy.round_timeout_s:g}"
                f" (deploy.min_clients={self.min_clients})"
            )
        # In client order, as in one process: the same sums to the last bit.
        self.server.aggregate(trained[c][1] for c in sorted(trained))
        ins = EvaluateIns(plan, self.server.global_weights)
        contents = {
            node: wire.encode_evaluate_ins(ins, self.config_yaml) for node, _, _ in trained.values()
        }
        rows = {}
        for node, reply in self.exchange("evaluate", contents, round_).items():
            res = wire.decode_evaluate_res(reply.content)
            if res.client not in trained or trained[res.client][0] != node:
                continue
            self.holders.add(node)
            _, upload, up = trained[res.client]
            received = down[node] + wire.payload_bytes(contents[node])
            rows[res.client] = self.server.row(upload, res, up, received)
        missing = tuple(c for c in range(self.config.data.clients) if c not in rows)
        seconds = time.perf_counter() - start
        return self.server.round_log(plan, self.server.table(rows), seconds, missing)


def config_of(context: Context) -> ExperimentConfig:
    """The run's fedlgr config from ``flwr run --run-config 'config="..." overrides="..."'``."""
    path = str(context.run_config.get("config", "")) or None
    overrides = shlex.split(str(context.run_config.get("overrides", "")))
    return load_config(path, overrides)


@app.main()
def main(grid: Grid, context: Context) -> None:
    from fedlgr.federated.experiment import Hooks, drive

    echo = functools.partial(print, flush=True)
    config = config_of(context)
    rounds = FlowerRounds(grid, config, echo)
    tags = {"runtime": "flower", "flower.run_id": str(context.run_id)}
    drive(rounds, config, Hooks(echo), tags=tags, what="robots behind a Flower SuperLink")
