"""A robot's client in the robot service: :func:`handle` answers each message with ``ClientSide``.
The server's config is read as data, its paths the robot's own; the private state stays on disk."""

from __future__ import annotations

import contextlib
import dataclasses
import os
from pathlib import Path

import torch
import yaml
from lightning.fabric import seed_everything

from fedlgr.core.client.side import ClientSide
from fedlgr.core.data.scenes import FederatedSplit
from fedlgr.core.state import to_device
from fedlgr.errors import FedlgrError, first_line
from fedlgr.shell.config import ExperimentConfig, check_sent_settings, config_from_data, to_yaml
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.splits import make_split
from fedlgr.shell.deploy.flower import masked, wire
from fedlgr.shell.deploy.flower.link import encode, state_dir
from fedlgr.shell.machine import torch_threads
from fedlgr.shell.run import checkpoint as ckpt
from fedlgr.shell.run.experiment import make_fabric
from fedlgr.shell.tracking.context import data_digest

_robots: dict[tuple[int | str, int], Robot] = {}  # (run, client): while the service lives
SERVER = "the server's config"
WEIGHTS = ("none", "imagenet")  # model.weights values that name no file


def node_setting(node_config: dict, key: str, default=None):
    value = node_config.get(key, default)
    if value is None:
        hint = " (a run without a roster, deploy.roster=none, takes it from there)"
        raise FedlgrError(
            f"SuperNode --node-config lacks {key!r}{hint if key == 'client' else ''}: start "
            "it with fedlgr deploy supernode --data DIR [--client K]"
        )
    return value


class Robot:
    """One robot's client between messages: built once per process, state on disk."""

    def __init__(self, config: ExperimentConfig, client: int, folder: Path, own_data: bool = False):
        check_client(config, client)
        fabric = make_fabric(config)
        if fabric.device.type == "cpu":
            torch.set_num_threads(torch_threads(config, 1))
        seed_everything(config.seed, verbose=False)
        scenes = load_scenes(config.data)
        split = own_split(scenes.table, config, client) if own_data else None
        split = split or make_split(scenes.table, config.data, config.continual.tasks)
        self.side = ClientSide(config, scenes, split, [client], fabric.device, fabric.autocast)
        self.client = self.side.clients[0]
        self.path = folder / f"client-{client}.ckpt"
        self.ended = -1  # the last task ended
        self.trained = -1  # the last round trained
        # The last message answered ([kind, round, round evaluated or -1]) and its encoded reply,
        # sent again unchanged (nothing trained) when a resumed server asks again.
        self.answered: list | None = None
        self.reply = b""
        self.digest = data_digest(config)  # of --data: its state is of this data only
        if self.path.is_file():
            state = ckpt.load(self.path)
            # its private state goes on only on the data it was trained on (as --resume checks)
            if (saved := state.get("data_digest", "")) and saved != self.digest:
                raise FedlgrError(
                    f"the data in --data {config.data.path} is not the data this robot's private "
                    f"state {self.path} was trained on (dataset digest {self.digest}, the state's "
                    f"{saved}): start the robot on its own data again, or start a new run"
                )
            self.side.load_state_dict(to_device({client: state["client"]}, fabric.device))
            self.ended = state["ended"]
            self.trained = state.get("trained", -1)
            self.answered, self.reply = state.get("answered"), state.get("reply", b"")
            print(f"client {client}: private state restored from {self.path}", flush=True)

    def save(self) -> None:
        state = {
            "client": to_device(self.client.state_dict(), "cpu"),
            "ended": self.ended,
            "trained": self.trained,
            "answered": self.answered,
            "reply": self.reply,
            "data_digest": self.digest,
        }
        ckpt.write(self.path, state)

    def answer(self, identity: list, work) -> bytes:
        """``work()``'s reply content, encoded, written to disk with the state it leaves;
        the reply already sent when ``identity`` is the message answered last."""
        if identity == self.answered and self.reply:
            print(f"{identity[0]} of round {identity[1]} answered before: same reply", flush=True)
            return self.reply
        if identity[0] == "train" and identity[1] <= self.trained:
            raise FedlgrError(
                f"round {identity[1]}: this robot has trained round {self.trained} already - "
                "the server was resumed from an older checkpoint than the robot's state "
                "(resume a Flower run with tracking.checkpoint=1)"
            )
        reply = encode(work())
        self.answered, self.reply = identity, reply
        if identity[0] == "train":
            self.trained = identity[1]
        self.save()
        return reply

    def train(self, ins):
        """The round's training; a robot that missed a task's last round ends that task first
        (``ClientSide`` begins a task whose first round it missed as it trains)."""
        plan = ins.plan
        for task in range(self.ended + 1, plan.task):
            if self.client.started >= task:
                self.client.task = self.side.tasks[task]
                self.side.end_task(self.client, plan.round, task)
                self.ended = task
        [res] = self.side.train(ins)
        return res

    def evaluate(self, ins):
        [res] = self.side.evaluate(ins)
        if ins.plan.last_of_task:
            self.ended = ins.plan.task
        return res


def check_client(config: ExperimentConfig, client: int) -> None:
    if not 0 <= client < config.data.clients:
        raise FedlgrError(
            f"--node-config client={client}: the run has data.clients="
            f"{config.data.clients} (clients 0 to {config.data.clients - 1})"
        )


def own_split(table, config: ExperimentConfig, client: int):
    """A robot's own folder as its whole shard: the split of a one-client run (``data.seed``,
    ``data.test_fraction``, its tasks as configured), labelled ``client``."""
    one = make_split(table, dataclasses.replace(config.data, clients=1), config.continual.tasks)
    shard = dataclasses.replace(one.clients[0], client=client)
    return FederatedSplit(one.train, one.test, one.test_tasks, [shard])


def robot(run_id: int | str, node_config: dict, config_yaml: str, slot: int | None = None) -> Robot:
    """This node's robot for the message's run, built on its first message, as client ``slot`` (the
    roster's) or, without a roster, the client its SuperNode names."""
    # (a slot other than the SuperNode's --client is refused by the ClientApp already)
    client = int(node_setting(node_config, "client")) if slot is None else slot
    _check_run(run_id)
    key = (run_id, client)
    if key not in _robots:
        config = robot_config(node_config, config_yaml)
        check_client(config, client)  # before anything of the run is written
        folder = state_dir(node_config) / f"run-{run_id}"
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)  # the robot's private state
        # What this robot runs; written beside and renamed over, so a link planted at
        # config.yaml is replaced, never written through.
        partial = folder / f".config.yaml.{os.getpid()}"
        partial.write_text(to_yaml(config))
        partial.replace(folder / "config.yaml")
        own = str(node_config.get("own-data", "false")).lower() == "true"
        _robots[key] = Robot(config, client, folder, own_data=own)
    return _robots[key]


class _DataLoader(yaml.SafeLoader):
    """YAML as plain data, without aliases (a few lines of them expand to gigabytes)."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            raise yaml.YAMLError("an alias (*name): not accepted")
        return super().compose_node(parent, index)


def robot_config(node_config: dict, config_yaml: str) -> ExperimentConfig:
    """The run's config on this robot: the server's settings read as data (no interpolation, no
    ``includes``), every setting that chooses where the robot reads or writes (``data.path``,
    ``data.cache_dir``, ``model.weights``) its SuperNode's, never the server's."""
    try:
        settings = yaml.load(config_yaml, Loader=_DataLoader)  # a SafeLoader
    except yaml.YAMLError as err:
        raise FedlgrError(f"{SERVER}: not valid YAML ({first_line(err)})") from None
    except RecursionError:  # thousands of levels: a message no fedlgr server sends
        raise FedlgrError(f"{SERVER}: nested too deeply to be a config") from None
    check_sent_settings(settings, SERVER)
    data, model, tracking, runtime = (
        _section(settings, name) for name in ("data", "model", "tracking", "runtime")
    )
    data["path"] = str(node_setting(node_config, "data-path"))
    data.pop("cache_dir", None)  # the robot's default unless its SuperNode names one
    if "cache-dir" in node_config:
        data["cache_dir"] = str(node_config["cache-dir"])
    if model.get("weights", "none") not in WEIGHTS:  # a file on the server
        if "weights" not in node_config:
            raise FedlgrError(
                f"{SERVER}: model.weights is a file, and a robot reads only its own: start "
                "its SuperNode with --weights FILE (its copy of those root weights)"
            )
        model["weights"] = str(node_config["weights"])
    for name in ("uri", "checkpoint_dir"):
        tracking.pop(name, None)
    tracking["enabled"] = False
    runtime.update(devices=1, num_nodes=1)
    if "threads" in node_config:
        runtime["threads"] = int(node_config["threads"])
    return config_from_data(settings, "the run's config on this robot")


def _section(settings: dict, name: str) -> dict:
    if settings.get(name) is None:
        settings[name] = {}
    section = settings[name]
    if not isinstance(section, dict):
        raise FedlgrError(f"{SERVER}: {name}: expected a mapping of settings")
    return section


def _check_run(run_id) -> None:
    """A run's state lives in ``<state-dir>/run-<id>``: an id that is not one (a path,
    ``..``) is refused before anything is written."""
    if not wire.RUN_KEY.fullmatch(str(run_id)):
        raise FedlgrError(f"run {str(run_id)[:80]!r}: not a run id; refused, nothing written")


@contextlib.contextmanager
def _malformed(kind: str):
    """A message fedlgr's server never sends (a record or field missing, a value of the
    wrong type) is one line, not a KeyError from the decoder."""
    try:
        yield
    except wire.MALFORMED as err:
        raise FedlgrError(
            f"the server's {kind} message is malformed ({type(err).__name__}: {err}); is the "
            "server running the same fedlgr as this robot?"
        ) from None


def handle(kind: str, run_id: int, node_config: dict, content) -> bytes:
    """The reply (Flower's encoding) to a ``train`` or ``evaluate`` message's content; the robot's
    state is kept under the server's run (its MLflow run: a resume is a new Flower run)."""
    with _malformed(kind):
        slot, run = wire.slot(content), wire.run_key(content) or str(run_id)
    _check_run(run)
    if kind == "train":
        with _malformed(kind):
            ins, evaluate, config_yaml = wire.decode_train_ins(content)
        client = robot(run, node_config, config_yaml, slot)
        identity = ["train", ins.plan.round, -1 if evaluate is None else evaluate.plan.round]

        secure = content.config_records.get(masked.RECORD)  # deploy.secagg: SecAgg+ round

        def work():
            evaluated = None if evaluate is None else client.evaluate(evaluate)  # last round's
            if secure is None:
                return wire.encode_train_res(client.train(ins), evaluated)
            return masked.encode_secure_res(client.train(ins), ins, secure, evaluated)

        return client.answer(identity, work)
    if kind == "evaluate":
        with _malformed(kind):
            ins, config_yaml = wire.decode_evaluate_ins(content)
        client = robot(run, node_config, config_yaml, slot)
        identity = ["evaluate", ins.plan.round, ins.plan.round]
        return client.answer(identity, lambda: wire.encode_evaluate_res(client.evaluate(ins)))
    raise FedlgrError(f"unknown message type {kind!r} (fedlgr answers train and evaluate)")
