"""Secure aggregation on robots (``deploy.secagg``): a round's training through Flower's own SecAgg+
workflow, so the server sees only the sum of the chosen robots' vectors (:mod:`.masked`), never one
robot's; :class:`Adapter` and :class:`Exchanges` fit fedlgr's messages into the workflow, and
:class:`SecAggPlus` keeps its drop-outs' bookkeeping to the protocol's."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np
import torch
from flwr.app import ArrayRecord, ConfigRecord, Context, Message, RecordDict
from flwr.common import FitIns, parameters_to_ndarrays
from flwr.common.secure_aggregation.secaggplus_constants import RECORD_KEY_CONFIGS, Key, Stage
from flwr.server.compat.grid_client_proxy import GridClientProxy
from flwr.server.compat.legacy_context import LegacyContext
from flwr.server.strategy import Strategy
from flwr.server.workflow import SecAggPlusWorkflow
from flwr.server.workflow.constant import MAIN_CONFIGS_RECORD, MAIN_PARAMS_RECORD
from flwr.server.workflow.constant import Key as WorkflowKey

from fedlgr.core.messages import TrainRes
from fedlgr.core.privacy import UNCLIPPED
from fedlgr.errors import FedlgrError
from fedlgr.shell.deploy.flower import masked, wire
from fedlgr.shell.deploy.flower.link import encode
from fedlgr.shell.deploy.flower.nodes import push_and_pull

if TYPE_CHECKING:
    from flwr.server.workflow.secure_aggregation.secaggplus_workflow import WorkflowState
    from flwr.serverapp import Grid

    from fedlgr.core.messages import RoundPlan

STAGES = {Stage.SETUP: "setup", Stage.SHARE_KEYS: "keys", Stage.UNMASK: "unmask"}
# MALFORMED, and what Flower's arithmetic raises on a masked vector of another shape
PROTOCOL_ERRORS = (*wire.MALFORMED, np.exceptions.AxisError)


class Exchanges:
    """The grid SecAgg+ talks through: the real one, polled every 0.2 s, its stages' bytes counted;
    the collect stage sends fedlgr's train messages (``contents``) and keeps the replies."""

    def __init__(self, grid: Grid, contents: dict[int, RecordDict]):
        self.grid, self.contents = grid, contents
        self.bytes: dict[str, float] = {}  # "secagg/setup_bytes_down" ...
        self.collected: dict[int, Message] = {}  # node -> its masked reply
        self.failures: dict[int, str] = {}  # node -> its error reply, any stage

    def send_and_receive(self, messages, *, timeout: float | None = None) -> list[Message]:
        messages = list(messages)
        stage = str(messages[0].content.config_records[RECORD_KEY_CONFIGS][Key.STAGE])
        if stage == Stage.COLLECT_MASKED_VECTORS:
            for m in messages:  # fedlgr's train message, with SecAgg's record added
                record = m.content.config_records[RECORD_KEY_CONFIGS]
                m.content = self.contents[m.metadata.dst_node_id]
                m.content.config_records[RECORD_KEY_CONFIGS] = record
        replies = push_and_pull(self.grid, messages, timeout if timeout is not None else 1e9)
        # an error reply may come from the SuperLink (a robot it has lost): named by its message
        to_node = {m.metadata.message_id: m.metadata.dst_node_id for m in messages}
        for reply in replies:
            if reply.has_error():
                reason = " ".join(str(reply.error.reason).split())
                node = to_node.get(reply.metadata.reply_to_message_id, reply.metadata.src_node_id)
                self.failures[node] = f"{stage}: {reason[:300]}"
        answered = {r.metadata.src_node_id for r in replies}
        for node in {m.metadata.dst_node_id for m in messages} - answered:
            self.failures.setdefault(node, f"{stage}: no reply")
        if stage == Stage.COLLECT_MASKED_VECTORS:
            self.collected = {r.metadata.src_node_id: r for r in replies if not r.has_error()}
        else:
            name = STAGES.get(stage, stage)
            down = sum(len(encode(m.content)) for m in messages)
            up = sum(len(encode(r.content)) for r in replies if not r.has_error())
            self.bytes[f"secagg/{name}_bytes_down"] = float(down)
            self.bytes[f"secagg/{name}_bytes_up"] = float(up)
        return replies


class SecAggPlus(SecAggPlusWorkflow):
    """Flower's SecAgg+ workflow (Bell et al. 2020, after Bonawitz et al. 2017), whose unmasking
    takes a robot that left the round early for one that left late: Flower 1.42 counts every robot
    sent the setup as one of the round's, so a robot gone before it shared its keys - one killed
    between two rounds, that the SuperLink still lists - is asked for in the unmask stage, where
    no robot holds a share of its keys (each answers an error) and the round fails ("Not enough
    shares to recover secret"). In the protocol such a robot is out of the round: no survivor
    masked its vector with it. So after each of the first two stages the round's robots, and each
    one's neighbours, are those that answered it; a robot that leaves after sharing its keys is
    unmasked from the survivors' shares, as in Flower's."""

    def setup_stage(self, grid: Grid, context: LegacyContext, state: WorkflowState) -> bool:
        return self.keep_active(super().setup_stage(grid, context, state), state)

    def share_keys_stage(self, grid: Grid, context: LegacyContext, state: WorkflowState) -> bool:
        return self.keep_active(super().share_keys_stage(grid, context, state), state)

    @staticmethod
    def keep_active(going: bool, state: WorkflowState) -> bool:
        """The round's robots, and each one's neighbours, those that answered the stage."""
        kept = set(state.active_node_ids)
        state.sampled_node_ids = kept
        state.nid_to_neighbours = {
            node: around & kept for node, around in state.nid_to_neighbours.items() if node in kept
        }
        return going


class Adapter(Strategy):
    """The legacy strategy SecAgg+ needs: ``configure_fit`` chooses the given nodes (what
    they are sent is fedlgr's, :class:`Exchanges`), ``aggregate_fit`` keeps the sum."""

    def __init__(self, grid: Grid, nodes: list[int], run_id: int):
        self.proxies = [GridClientProxy(n, grid, run_id) for n in nodes]
        self.mean: np.ndarray | None = None  # the unmasked vector over its robots
        self.count = 0  # the robots in it

    def configure_fit(self, server_round, parameters, client_manager):
        return [(proxy, FitIns(parameters, {})) for proxy in self.proxies]

    def aggregate_fit(self, server_round, results, failures):
        if results:
            [self.mean] = parameters_to_ndarrays(results[0][1].parameters)
            self.count = len(results)
        return None, {}

    def initialize_parameters(self, client_manager):
        return None

    def configure_evaluate(self, server_round, parameters, client_manager):
        return []

    def aggregate_evaluate(self, server_round, results, failures):
        return None, {}

    def evaluate(self, server_round, parameters):
        return None


class SecureAggregation:
    """A round's training and aggregation under SecAgg+ for :class:`FlowerRounds`
    (``rounds``: its nodes, its refusals and the ServerSide)."""

    def __init__(self, rounds):
        self.rounds, self.server = rounds, rounds.server
        self.settings = rounds.config.deploy.secagg
        self.summed: tuple[np.ndarray, int] | None = None
        self.round = 0  # the round being summed
        self.figures: dict[str, float] = {}
        self.refused: list[str] = []  # "round 2: its mean update's norm ..." (a tag)

    def train(self, plan: RoundPlan, chosen: list[int]) -> tuple[dict, dict]:
        """The chosen robots' training, summed by SecAgg+: their figures by client (``client ->
        (node, TrainRes without tensors, masked bytes)``) and each node's bytes down."""
        rounds = self.rounds
        privacy = self.server.privacy
        record = masked.message_settings(self.settings, 0 if privacy is None else privacy.bound)
        contents = rounds.train_messages(plan, chosen)  # all with the update's origin
        for content in contents.values():
            content[masked.RECORD] = ConfigRecord(record)
            wire.stamp_run(content, rounds.run_id or "")
        down = {node: wire.payload_bytes(content) for node, content in contents.items()}
        if len(contents) < 2:
            raise FedlgrError(
                f"round {plan.round}: {len(contents)} chosen robot online; deploy.secagg "
                "needs 2 or more to hide each update"
            )
        grid, adapter = Exchanges(rounds.grid, contents), Adapter(rounds.grid, list(contents), 0)
        started = time.monotonic()
        self.round = plan.round
        secure_sum(grid, adapter, plan.round, self.settings, rounds.config.deploy.round_timeout_s)
        seconds = time.monotonic() - started
        failed = "".join(f"; {rounds.nodes.name(n)}: {why}" for n, why in grid.failures.items())
        rounds.echo(
            f"round {plan.round}, secure train: {adapter.count} of {len(contents)} robots in "
            f"the sum ({seconds:.1f} s){failed}"
        )
        if adapter.mean is None:
            raise FedlgrError(
                f"round {plan.round}: SecAgg+ gave no sum (fewer robots than its threshold "
                f"answered within deploy.round_timeout_s={rounds.config.deploy.round_timeout_s:g})"
                f"{failed}"
            )
        self.summed = (adapter.mean, adapter.count)
        self.figures = grid.bytes | {"secagg/seconds": seconds, "secagg/robots": adapter.count}
        trained = {}
        for node, reply in grid.collected.items():
            self.keep(trained, node, reply, plan.round)
        return trained, down

    def keep(self, trained: dict, node: int, reply: Message, round_: int) -> None:
        """A robot's figures from its masked reply (in the clear beside the vector)."""
        slot = self.rounds.nodes.slots.get(node)
        try:
            records = reply.content.config_records
            client = int(records["report"]["client"])
            figures = {str(k): float(v) for k, v in records["figures"].items()}
            size = sum(len(b) for b in records[RECORD_KEY_CONFIGS][Key.MASKED_PARAMETERS])
        except wire.MALFORMED as err:
            self.rounds.refuse(round_, node, slot, "upload", f"cannot be read ({err!r:.200})")
            return
        if slot is not None and client != slot:
            self.rounds.refuse(round_, node, slot, "upload", f"it claims to be client {client}'s")
            return
        trained[client] = (node, TrainRes(client, {}, 0, figures, {}), size)

    def release(self, unread: dict[int, str]) -> None:
        """The next global tensors from the round's sum (``ServerSide.update``, which adds DP's
        noise), if the sum passes its checks. ``unread``: robots whose clear records were refused,
        recorded though SecAgg+ cannot take their updates out of the sum."""
        self.server.refused = {
            client: f"upload: {why} (its update is in the secure sum)"
            for client, why in unread.items()
        }
        mean, count = self.summed
        try:
            sums, total, payloads = unpack(mean * count, count, self.server, self.settings)
        except ValueError as err:
            self.rounds.echo(
                f"round {self.round}: the secure sum of {count} robots is refused: {err}; the "
                "global model stays"
            )
            self.figures["secagg/sum_refused"] = 1.0
            self.refused.append(f"round {self.round}: {err}")
            self.rounds.tag("fedlgr.secagg_refused", "; ".join(self.refused)[-5000:])
            return
        self.figures["secagg/sum_refused"] = 0.0
        privacy = self.server.privacy  # under DP the sum is divided by q N, not by N / W
        bound = masked.error_bound(self.settings, count, total, privacy is not None)
        self.figures["secagg/error_bound"] = bound / (privacy.expected if privacy else 1)
        self.server.update(sums, total, payloads, count)


def secure_sum(grid: Exchanges, adapter: Adapter, round_: int, secagg, timeout: float) -> None:
    """Round ``round_``'s SecAgg+ (``secagg``: ``deploy.secagg``) over ``grid`` (an
    :class:`Exchanges`) with ``adapter``'s nodes, each stage waiting ``timeout`` seconds; the
    unmasked mean lands in ``adapter``."""
    workflow = SecAggPlus(
        secagg.shares,
        secagg.threshold,
        max_weight=1.0,  # every robot weighs 1: its weight is in its vector (.masked)
        clipping_range=float(secagg.clipping_range),
        quantization_range=int(secagg.quantization_range),
        timeout=timeout,
    )
    state = RecordDict()
    state[MAIN_CONFIGS_RECORD] = ConfigRecord({WorkflowKey.CURRENT_ROUND: round_})
    state[MAIN_PARAMS_RECORD] = ArrayRecord()  # no global parameters: fedlgr sends its own
    context = LegacyContext(Context(0, 0, {}, state, {}), strategy=adapter)
    try:
        workflow(grid, context)
    except PROTOCOL_ERRORS as err:
        raise FedlgrError(
            f"round {round_}: SecAgg+ failed ({type(err).__name__}: {err}); a robot sent "
            "a masked vector of another layout"
        ) from None


def unpack(summed: np.ndarray, count: int, server, settings) -> tuple[dict, float, dict]:
    """What ``ServerSide.update`` takes from the sum of ``count`` robots' vectors (:mod:`.masked`):
    tensor, sample-count and payload sums, under DP the bits' sum rounded to ``k - total / 2``. A
    sum not finite, under one sample per robot, over the norm honest robots' vectors keep to
    (:func:`~.masked.over_bound`) or, without DP, whose mean has a BatchNorm variance below 0 (no
    mean of honest robots' variances has) is refused (``ValueError``)."""
    dp = server.privacy is not None
    payload = server.strategy.payload_template()
    parts = masked.layout(server.global_weights, payload, dp)
    found = masked.split(np.asarray(summed, dtype=np.float64), parts)
    if not all(bool(torch.isfinite(v).all()) for v in found.values()):
        raise ValueError("it holds values that are not finite")
    scale = 1 if dp else settings.max_samples
    total = round(float(found.pop(masked.WEIGHT)) * scale)
    if total < count:
        raise ValueError(f"its sample count {total} is under one per robot ({count})")
    clip = 0.0 if server.privacy is None else float(server.privacy.bound)  # this round's
    if (why := masked.over_bound(found, count, total, settings, clip)) is not None:
        raise ValueError(why)
    g = server.global_weights
    sums = {k: scale * found[f"w/{k}"] + total * g[k].double() for k in g}
    for key in (k for k in sums if k.endswith("running_var") and not dp):
        if bool((sums[key] < 0).any()):  # what a plain round refuses in an upload, in the mean
            raise ValueError(
                f"it would make {key} a variance below 0 (min {float(sums[key].min() / total):.3g})"
            )
    payloads = {k: found[f"p/{k}"] for k in sorted(payload)}
    if dp:
        within = round(float(found[UNCLIPPED]) + total / 2)  # k, a whole number
        payloads[UNCLIPPED] = torch.tensor(within - total / 2, dtype=torch.float64)
    return sums, float(total), payloads
