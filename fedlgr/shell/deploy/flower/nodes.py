"""The robots of a run as the ServerApp sees them: a node is admitted if the roster lists its key
(in the roster's slot; without a roster any node), else refused and never sent a message."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from cryptography.exceptions import UnsupportedAlgorithm
from flwr.app import Message, RecordDict
from flwr.serverapp import Grid

from fedlgr.errors import FedlgrError
from fedlgr.shell.config import ExperimentConfig
from fedlgr.shell.deploy.flower import wire
from fedlgr.shell.deploy.roster import Roster, fingerprint

POLL_S = 0.2  # how often the server asks the SuperLink for replies


def quorum(clients: int) -> int:
    """The uploads a round needs by default (``deploy.min_clients``): half the robots,
    at least one - one robot's drop-out does not end a run."""
    return max(1, math.ceil(clients / 2))


class Nodes:
    """The admitted nodes, their client slots and names, the refused ones and the last exchange's
    errors; ``tag`` records a run-level fact in MLflow."""

    def __init__(
        self,
        grid: Grid,
        config: ExperimentConfig,
        roster: Roster | None,
        echo: Callable[[str], object],
        tag: Callable[[str, str], None],
    ):
        self.grid, self.config, self.roster = grid, config, roster
        self.echo, self.tag = echo, tag
        self.slots: dict[int, int | None] = {}  # admitted node -> its client (None: no roster)
        self.names: dict[int, str] = {}  # admitted node -> "robot0 (client 0)"
        self.refused: dict[int, str] = {}  # node -> why it is sent nothing
        self.failures: dict[int, str] = {}  # node -> its error in the last exchange

    def online(self) -> list[int]:
        """The admitted nodes online now, by client slot; a node seen for the first time
        is admitted or refused (see the module's docstring)."""
        nodes = list(self.grid.get_nodes())
        for info in nodes:
            node = info.node_id
            if node in self.slots or node in self.refused:
                continue
            if self.roster is None:
                self.slots[node], self.names[node] = None, f"node {node}"
                continue
            member = self.roster.member(bytes(info.public_key))
            if member is None:
                try:
                    key = fingerprint(bytes(info.public_key))
                except (ValueError, TypeError, UnsupportedAlgorithm):
                    key = "(none: no SuperNode authentication)"
                self.refuse(node, f"its key {key} is not on the roster {self.roster.path}")
            elif member.client >= self.config.data.clients:
                self.refuse(node, f"{member}: the run has data.clients={self.config.data.clients}")
            else:
                self.slots[node], self.names[node] = member.client, str(member)
                self.echo(f"{member} is online (node {node})")
        here = {info.node_id for info in nodes}
        admitted = [n for n in self.slots if n in here and n not in self.refused]
        return sorted(admitted, key=lambda n: (self.slots[n] is None, self.slots[n] or 0, n))

    def refuse(self, node: int, why: str) -> None:
        self.refused[node] = why
        self.slots.pop(node, None)
        self.echo(f"refused node {node}: {why}; it is sent no work")
        self.tag("fedlgr.refused", "; ".join(f"node {n}: {w}" for n, w in self.refused.items()))

    def wait_for_robots(self, min_clients: int) -> None:
        """Until every client's robot has joined, or ``deploy.join_timeout_s``; fewer than
        ``min_clients`` by then is an error."""
        want = self.config.data.clients
        deadline = time.monotonic() + self.config.deploy.join_timeout_s
        nodes: list[int] = []
        while time.monotonic() < deadline:
            nodes = self.online()
            if len(nodes) >= want:
                break
            time.sleep(0.5)
        if len(nodes) < min_clients:
            raise FedlgrError(
                f"{len(nodes)} of {want} robots joined within deploy.join_timeout_s="
                f"{self.config.deploy.join_timeout_s:g} (deploy.min_clients={min_clients})"
            )
        self.echo(f"{len(nodes)} of {want} robots joined: {', '.join(self.name(n) for n in nodes)}")
        self.tag("fedlgr.robots", ", ".join(self.name(n) for n in nodes))

    def name(self, node: int) -> str:
        return self.names.get(node, f"node {node}")

    def exchange(
        self,
        kind: str,
        contents: dict[int, RecordDict],
        round_: int,
        run_id: str | None,
        label: str = "",
        kinds: dict[int, str] | None = None,
    ):
        """Send ``contents`` (node -> content) as messages of type ``kind`` (or a node's in
        ``kinds``), stamped with the MLflow ``run_id``; the replies back in time, by node. Error
        replies are reported, not raised; a robot claiming another slot is refused."""
        kinds = kinds or {}
        messages = [
            Message(
                wire.stamp_run(content, run_id or ""),
                dst_node_id=node,
                message_type=kinds.get(node, kind),
                group_id=str(round_),
            )
            for node, content in contents.items()
        ]
        started = time.monotonic()
        replies = push_and_pull(self.grid, messages, self.config.deploy.round_timeout_s)
        seconds = time.monotonic() - started
        # An error reply may come from the SuperLink itself (a robot gone offline): the
        # robot is the one the message was sent to.
        to_node = {m.metadata.message_id: m.metadata.dst_node_id for m in messages}
        out = {}
        self.failures = {}
        for reply in replies:
            node = to_node.get(reply.metadata.reply_to_message_id, reply.metadata.src_node_id)
            if reply.has_error():
                reason = " ".join(str(reply.error.reason).split())
                self.failures[node] = reason
                robot = self.name(node)
                self.echo(f"round {round_}, {label or kind}: {robot} failed: {reason}")
                if "the run's roster gives its key client" in reason:
                    self.refuse(node, f"{robot} claims another slot")
            else:
                out[node] = reply
        silent = [self.name(n) for n in contents if n not in out and n not in self.failures]
        late = f"; no reply from {', '.join(silent)}" if silent else ""
        self.echo(
            f"round {round_}, {label or kind}: {len(out)} of {len(messages)} replies "
            f"({seconds:.1f} s){late}"
        )
        return out


def push_and_pull(grid, messages: list[Message], timeout: float) -> list[Message]:
    """``Grid.send_and_receive``, polled every ``POLL_S`` instead of its 3 s: the replies to
    ``messages`` that came within ``timeout`` seconds."""
    pending = {i for i in grid.push_messages(messages) if i}
    replies: list[Message] = []
    deadline = time.monotonic() + timeout
    while pending and time.monotonic() < deadline:
        for reply in grid.pull_messages(list(pending)):
            pending.discard(reply.metadata.reply_to_message_id)
            replies.append(reply)
        if pending:
            time.sleep(POLL_S)
    return replies
