"""The ServerApp: ``fedlgr run``'s run life (:class:`~fedlgr.shell.run.life.RunLife`) around
:class:`FlowerRounds`, whose clients are robots behind a SuperLink, spoken to in :mod:`.wire`."""

from __future__ import annotations

import functools
import logging
import shlex
import time

import torch
from flwr.app import Context, Message, RecordDict
from flwr.serverapp import Grid, ServerApp

from fedlgr.core.evaluation import eval_set
from fedlgr.core.messages import EvaluateIns, EvaluateRes, RoundPlan, TrainRes
from fedlgr.core.records import RoundLog
from fedlgr.core.rounds import EpochProgress
from fedlgr.core.schedule import ALL, schedule
from fedlgr.core.server.evaluate import ServerEvaluation, serve_round
from fedlgr.core.server.screen import claim_refusal, figures_refusal
from fedlgr.core.server.side import ServerSide
from fedlgr.core.state import rng_states, set_rng_states, to_device
from fedlgr.errors import FedlgrError, first_line
from fedlgr.shell.checks.experiment import check_robots_are_real
from fedlgr.shell.config import ExperimentConfig, load_config, robot_yaml
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.splits import make_split
from fedlgr.shell.deploy.flower import wire
from fedlgr.shell.deploy.flower.nodes import Nodes, quorum
from fedlgr.shell.deploy.flower.secure import SecureAggregation
from fedlgr.shell.deploy.roster import roster_of
from fedlgr.shell.run.life import Hooks, RunLife
from fedlgr.shell.run.resume import resume_point
from fedlgr.shell.tracking.mlflow_run import open_client, tracking_uri

app = ServerApp()


class OneLineErrors(logging.Filter):
    """Flower logs the exception a ServerApp raises with its traceback (``flwr`` logger,
    ``run_serverapp``), and ``flwr run --stream`` shows that to the user before ``fedlgr deploy
    run`` prints the one line a :class:`FedlgrError` is: its traceback goes (it was ~20 lines
    before "two robots dropped out"); any other exception keeps its own."""

    def filter(self, record: logging.LogRecord) -> bool:
        raised = record.exc_info[1] if record.exc_info else None
        if isinstance(raised, FedlgrError):
            record.msg, record.args = "%s: %s", (record.getMessage(), first_line(raised))
            record.exc_info, record.exc_text = None, None
        return True


logging.getLogger("flwr").addFilter(OneLineErrors())  # this process runs the ServerApp
CPU = torch.device("cpu")


class FlowerRounds:
    """A run's rounds (:class:`fedlgr.core.rounds.Rounds`) with the clients on the robots
    (:class:`~fedlgr.shell.deploy.flower.nodes.Nodes`)."""

    def __init__(self, grid: Grid, config: ExperimentConfig, echo=print):
        check_robots_are_real(config)
        self.grid, self.config, self.echo = grid, config, echo
        self.run_id: str | None = None  # the MLflow run (for tags), once it exists
        self.tags: dict[str, str] = {}
        roster = roster_of(config)
        self.nodes = Nodes(grid, config, roster, echo, self.tag)
        # client -> "robot2 (client 2)", and the most training scenes it may claim
        self.names = {m.client: str(m) for m in roster.members} if roster is not None else {}
        self.capacity = roster.capacity if roster is not None else {}
        # refused on receipt: round -> client -> why (uploads: aggregation's; scores: the record's)
        self.unread: dict[int, dict[int, str]] = {}
        self.bad_scores: dict[int, str] = {}
        self.server = ServerSide(config, robots=True)
        if config.federated.fraction < 1 and roster is None:
            raise FedlgrError(
                f"federated.fraction={config.federated.fraction:g} on robots needs a roster "
                "(deploy.roster): the server chooses clients, so it must know which robot "
                "is which client"
            )
        if config.federated.evaluate != "all":
            raise FedlgrError(
                f"federated.evaluate={config.federated.evaluate} on robots: every robot "
                "scores each round's global tensors on Flower (the scores come with its "
                "next exchange); use federated.evaluate=all"
            )
        if config.federated.eval_every != 1:
            raise FedlgrError(
                f"federated.eval_every={config.federated.eval_every} on robots: every robot "
                "scores each round's global tensors on Flower; use federated.eval_every=1"
            )
        # federated.server_eval: the server scores the global model on its own copy of the
        # test scenes (data.path on the SuperLink's machine).
        self.server_eval = server_evaluation(config) if config.federated.server_evaluates else None
        # where a robot scores the very model the server does (every tensor of values shared;
        # BatchNorm's step counter is not, and does not change a score), the server's scores
        # are the check of its claim
        self.served: dict[str, float] = {}
        self.checks_claims = self.server_eval is not None and all(
            k in self.server.keys
            for k, v in self.server_eval.model.state_dict().items()
            if v.is_floating_point()
        )
        self.config_yaml = robot_yaml(config)
        self.holders: set[int] = set()  # nodes that hold the current global tensors
        self.min_clients = config.deploy.min_clients or quorum(config.data.clients)
        self.joined = False
        self.steps = schedule(config)
        # (plan, uploads by client, bytes down by node, failures by node) of the next
        # round, trained in the exchange that evaluated this one (with_next_round)
        self.pending: tuple[RoundPlan, dict, dict[int, int], dict[int, str]] | None = None
        self.missed: list[str] = []  # "round 2: robot1 (client 1)"
        self.secure = SecureAggregation(self) if config.deploy.secagg.enabled else None

    # ------------------------------------------------------------------ MLflow tags

    def started(self, run_id: str) -> None:
        """``on_start`` (:class:`fedlgr.shell.run.life.Hooks`): the MLflow run exists;
        tags said before go to it."""
        self.run_id = run_id
        for key, value in self.tags.items():
            self.tag(key, value)

    def tag(self, key: str, value: str) -> None:
        self.tags[key] = value
        if self.run_id is not None and self.config.tracking.enabled:
            open_client(tracking_uri(self.config)).set_tag(self.run_id, key, value[:5000])

    # ------------------------------------------------------------------ rounds

    local_clients = 0  # no client trains in this process: they are on the robots

    def run_round(self, plan: RoundPlan, progress: EpochProgress | None = None) -> RoundLog:
        """One round: the chosen clients' training (or the uploads the previous exchange brought
        back), aggregation, and every client's evaluation, with ``with_next_round`` in the next
        round's training exchange. ``progress`` is never called: no client trains here."""
        if not self.joined:
            self.nodes.wait_for_robots(self.min_clients)
            self.joined = True
        start = time.perf_counter()
        chosen = self.server.chosen(plan)
        if self.pending is not None and self.pending[0] == plan:
            _, trained, down, failures = self.pending
        elif self.secure is not None:  # deploy.secagg: the server gets the sum only
            (trained, down), failures = self.secure.train(plan, chosen), {}
        else:
            trained, down = self.train(plan, chosen)
            failures = dict(self.nodes.failures)
        self.pending = None
        self.check_quorum(plan.round, trained, chosen, failures)
        # In client order, as in one process: the same sums to the last bit.
        unread = self.unread.pop(plan.round, {})

        def aggregate() -> dict[str, float]:
            if self.secure is None:
                uploads = (trained[c][1] for c in sorted(trained))
                self.server.aggregate(uploads, self.capacity, unread)
                return {}
            self.secure.release(unread)
            return self.secure.figures

        served = serve_round(self.server, self.server_eval, plan, aggregate)
        self.served = served[0]
        self.bad_scores = {}
        rows = self.evaluate(plan, chosen, trained, down)
        missing = tuple(c for c in range(self.config.data.clients) if c not in rows)
        if missing:
            self.record_missing(plan.round, missing, trained)
        return self.server.round_log(
            plan,
            self.server.table(rows),
            time.perf_counter() - start,
            missing,
            chosen,
            served,
            names=self.names,
            bad_scores=self.bad_scores,  # their rows are left out
        )

    def refuse(self, round_: int, node: int, client: int | None, what: str, why: str) -> None:
        """What a robot sent in round ``round_`` is not taken: its ``upload`` (named by that round's
        aggregation) or its ``scores``; a robot whose client is unknown is named here."""
        if client is None:
            self.echo(f"round {round_}: refused {self.nodes.name(node)}'s {what}: {why}")
        elif what == "upload":
            self.unread.setdefault(round_, {})[client] = why
        else:
            self.bad_scores[client] = why

    def check_quorum(self, round_: int, trained: dict, chosen: list[int], failures: dict) -> None:
        """Enough uploads to aggregate: ``deploy.min_clients`` (at most the clients the
        strategy chose)."""
        needed = min(self.min_clients, len(chosen))
        if len(trained) >= needed:
            return
        causes = "".join(f"; {self.nodes.name(n)}: {why}" for n, why in failures.items())
        of = f"{len(chosen)} chosen" if len(chosen) < self.config.data.clients else ""
        raise FedlgrError(
            f"round {round_}: {len(trained)} of {of or self.config.data.clients} robots sent "
            f"their update within deploy.round_timeout_s={self.config.deploy.round_timeout_s:g}"
            f" (deploy.min_clients={self.min_clients}){causes}"
        )

    def evaluate(self, plan: RoundPlan, chosen: list[int], trained: dict, down: dict) -> dict:
        """Every client's figures in round ``plan``: the robots that trained and those not chosen
        score the new global tensors (a chosen robot that sent nothing is missing); with
        ``with_next_round`` the next round's chosen robots train in the same exchange."""
        round_ = plan.round
        evaluate = EvaluateIns(plan, self.server.global_weights)
        following = self.next_plan(round_)
        serving = {node: client for client, (node, _, _) in trained.items()}
        nodes = sorted({*self.nodes.online(), *(n for n in serving if n in self.nodes.slots)})
        # the robots that trained, and those of clients the strategy did not choose
        scoring = [n for n in nodes if n in serving or self.nodes.slots[n] not in (None, *chosen)]
        contents, kinds = self.evaluation_messages(evaluate, following, scoring, nodes)
        received = {node: wire.payload_bytes(content) for node, content in contents.items()}
        # what a combined message carries for the next round alone - the strategy's payload -
        # is that round's download, as in one process
        ahead = {
            node: wire.train_payload_bytes(c) for node, c in contents.items() if node in scoring
        }
        kind = "evaluate" if following is None else "train"
        label = kind if following is None else f"evaluate + round {round_ + 1} train"
        rows, uploads = {}, {}
        self.holders = set()
        replies = self.nodes.exchange(kind, contents, round_, self.run_id, label, kinds)
        for node, reply in replies.items():
            if kinds.get(node, kind) != "evaluate":
                self.keep_upload(uploads, node, reply, round_ + 1)
            res = self.scores(reply, node, round_, kinds.get(node, kind))
            if res is None or node not in scoring:
                continue
            if serving.get(node, self.nodes.slots.get(node)) != res.client:
                claim = f"they claim to be client {res.client}'s"
                self.refuse(round_, node, self.nodes.slots.get(node), "scores", claim)
                continue
            why = figures_refusal(res.figures, self.server.round_keys)
            if why is None and self.checks_claims:
                why = claim_refusal(res.figures, self.served)
            if why is not None:
                self.refuse(round_, node, res.client, "scores", why)
                continue
            self.holders.add(node)
            upload = trained.get(res.client)
            taken = down.get(node, 0) + received[node] - ahead[node]
            if upload is None:  # not chosen: it downloads to score
                rows[res.client] = self.server.row(None, res, 0, taken)
            else:
                rows[res.client] = self.server.row(upload[1], res, upload[2], taken)
        if following is not None:
            # what the next round's rows count as downloaded: its payload for a robot that
            # scored here (the tensors served both), the whole message for one that did not
            following_down = {
                n: ahead[n] if n in scoring else received[n] for n, _, _ in uploads.values()
            }
            self.pending = (following, uploads, following_down, dict(self.nodes.failures))
        return rows

    def scores(self, reply: Message, node: int, round_: int, kind: str) -> EvaluateRes | None:
        """The scores a reply carries (None: none, or none that can be read)."""
        try:
            if kind == "evaluate":
                return wire.decode_evaluate_res(reply.content)
            return wire.decode_evaluated(reply.content)
        except wire.MALFORMED as err:
            why = f"cannot be read ({type(err).__name__}: {first_line(err)[:200]})"
            self.refuse(round_, node, self.nodes.slots.get(node), "scores", why)
            return None

    def evaluation_messages(
        self, evaluate: EvaluateIns, following: RoundPlan | None, scoring: list[int], nodes
    ) -> tuple[dict[int, RecordDict], dict[int, str]]:
        """The round's evaluation messages (``scoring``: the nodes that score it) and, with
        ``following``, the next round's training for its chosen robots in the same
        messages; the message type of each that is not the exchange's own."""
        contents: dict[int, RecordDict] = {}
        kinds: dict[int, str] = {}
        chosen_next = set() if following is None else set(self.server.chosen(following))
        for node in nodes:
            slot = self.nodes.slots.get(node)
            trains = following is not None and (slot is None or slot in chosen_next)
            if node in scoring and not trains:
                contents[node] = wire.encode_evaluate_ins(evaluate, self.config_yaml, slot)
                kinds[node] = "evaluate"
            elif node in scoring:  # scores this round's tensors, then trains on them
                ins = self.server.train_ins(following, slot)
                contents[node] = wire.encode_train_ins(ins, self.config_yaml, evaluate, slot)
            elif trains:  # missed this round: trains the next one on the tensors it is sent
                ins = self.server.train_ins(following, slot, holds_global=False)
                contents[node] = wire.encode_train_ins(ins, self.config_yaml, client=slot)
        return contents, kinds

    def record_missing(self, round_: int, missing: tuple[int, ...], trained: dict) -> None:
        by_client = {c: self.nodes.name(n) for c, (n, _, _) in trained.items()}
        by_client |= {s: self.nodes.names[n] for n, s in self.nodes.slots.items() if s is not None}
        self.missed.append(
            f"round {round_}: " + ", ".join(by_client.get(c, f"client {c}") for c in missing)
        )
        self.tag("fedlgr.missing_robots", "; ".join(self.missed))

    def next_plan(self, round_: int) -> RoundPlan | None:
        """The plan of the round after ``round_`` where its training goes with this
        round's evaluation (``deploy.evaluate=with_next_round``), else None."""
        if self.secure is not None:  # SecAgg+'s exchanges train; the evaluation is its own
            return None
        if self.config.deploy.evaluate != "with_next_round" or round_ >= len(self.steps):
            return None
        return self.steps[round_]  # steps are 1-based rounds: this is round_ + 1

    def train(self, plan: RoundPlan, chosen: list[int]):
        """A training exchange of its own (round 1, ``deploy.evaluate=separate``) with the
        robots of the ``chosen`` clients: the uploads by client, and each node's bytes down."""
        contents = self.train_messages(plan, chosen, self.holders)
        trained: dict[int, tuple[int, TrainRes, int]] = {}  # client -> (node, upload, bytes)
        for node, reply in self.nodes.exchange("train", contents, plan.round, self.run_id).items():
            self.keep_upload(trained, node, reply, plan.round)
        return trained, {node: wire.payload_bytes(c) for node, c in contents.items()}

    def train_messages(self, plan: RoundPlan, chosen: list[int], holders=frozenset()) -> dict:
        """The round's train message to each online robot of the ``chosen`` clients (``holders``:
        the nodes that hold the current global tensors, which are not sent to them)."""
        contents = {}
        for node in self.nodes.online():
            slot = self.nodes.slots[node]
            if slot is None or slot in chosen:
                ins = self.server.train_ins(plan, slot, holds_global=node in holders)
                contents[node] = wire.encode_train_ins(ins, self.config_yaml, client=slot)
        return contents

    def keep_upload(self, trained: dict, node: int, reply: Message, round_: int) -> None:
        slot = self.nodes.slots.get(node)
        try:
            res = wire.decode_train_res(reply.content)
        except wire.MALFORMED as err:
            why = f"cannot be read ({type(err).__name__}: {first_line(err)[:200]})"
            self.refuse(round_, node, slot, "upload", why)
            return
        name = self.nodes.name
        if slot is not None and res.client != slot:
            self.refuse(round_, node, slot, "upload", f"it claims to be client {res.client}'s")
            return
        if res.client in trained:
            self.echo(
                f"round {round_}: {name(trained[res.client][0])} and {name(node)} "
                f"both serve client {res.client}; {name(node)}'s upload is ignored"
            )
            return
        if (why := figures_refusal(res.figures, self.server.round_keys)) is not None:
            self.refuse(round_, node, res.client, "upload", f"its figures: {why}")
            return
        trained[res.client] = (node, res, wire.payload_bytes(reply.content))

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict:
        """What the server holds between rounds (the robots keep theirs): the global tensors and
        strategy state, the next round's uploads already trained, which robots hold the global
        tensors, the drop-outs so far, and the random generators."""
        pending = None
        if self.pending is not None:
            plan, trained, down, failures = self.pending
            # an upload's fields by name (shallow: the tensors as they are)
            uploads = {c: [n, dict(vars(res)), b] for c, (n, res, b) in trained.items()}
            pending = {
                "plan": [plan.round, plan.task, plan.first_of_task, plan.last_of_task],
                "uploads": uploads,
                "down": down,
                "failures": failures,
            }
        server = {
            "server": to_device(self.server.state_dict(), "cpu"),
            "pending": pending,
            "holders": sorted(self.holders),
            "missed": list(self.missed),
            "unread": self.unread,
        }
        return {"server": server, "clients": {}, "rng": [rng_states()]}

    def load_state_dict(self, state: dict) -> None:
        held = state["server"]
        self.server.load_state_dict(held["server"], "cpu")
        self.holders = set(held["holders"])
        self.missed = list(held["missed"])
        self.unread = {int(r): dict(found) for r, found in held.get("unread", {}).items()}
        pending = held["pending"]
        if pending is not None:
            trained = {
                int(c): (n, TrainRes(**res), b) for c, (n, res, b) in pending["uploads"].items()
            }
            plan = RoundPlan(*pending["plan"])
            self.pending = (plan, trained, dict(pending["down"]), dict(pending["failures"]))
        set_rng_states(state["rng"][0])


def server_evaluation(config: ExperimentConfig) -> ServerEvaluation:
    """The server's own copy of the test scenes (``federated.server_eval``), from ``data.path`` on
    the SuperLink's machine, split as the robots split them (only the shared test set is used)."""
    scenes = load_scenes(config.data)
    split = make_split(scenes.table, config.data)
    tasks = list(config.continual.tasks) or [ALL]
    channels_last = config.model.channels_last and scenes.images is not None
    return ServerEvaluation(config, eval_set(scenes, split, tasks, CPU, channels_last))


@app.main()
def main(grid: Grid, context: Context) -> None:
    echo = functools.partial(print, flush=True)
    # the run's config from ``flwr run --run-config 'config="..." overrides="..."'``
    path = str(context.run_config.get("config", "")) or None
    config = load_config(path, shlex.split(str(context.run_config.get("overrides", ""))))
    rounds = FlowerRounds(grid, config, echo)
    resume = str(context.run_config.get("resume", ""))  # fedlgr deploy run --resume [RUN_ID]
    resumed = resume_point(None, config, True if resume == "latest" else resume)
    tags = {"runtime": "flower", "flower.run_id": str(context.run_id)}
    life = RunLife(
        config,
        Hooks(echo, on_start=rounds.started),
        tags=tags,
        what="robots behind a Flower SuperLink",
        resumed=resumed,
    )
    life.run(rounds)
