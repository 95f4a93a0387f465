"""A robot's client between Flower messages: its data, model and private state.

:func:`handle` answers one message (``train`` or ``evaluate``) with
:class:`fedlgr.federated.client_side.ClientSide`, the very code the in-process
orchestrator runs. It runs inside the robot service (:mod:`.service`), a long-lived
process per robot, so torch, the data and the models are loaded once, not per message.

The robot's SuperNode says where its data is and which client it is (``--node-config
'data-path="/data/manners-db" client=0'``; optional ``state-dir``, ``cache-dir``,
``weights``, ``threads``). The server sends the run's resolved config with every message;
the robot reads it as data (:func:`robot_config`: no interpolation, no ``includes``, and
every path it reads or writes is its SuperNode's, never the server's), loads its folder
and takes its shard (``data.clients`` and ``data.seed`` fix the split, as in ``fedlgr run``).

Its private state - the top, the optimiser, FedLGR's generator and labeller, CL
importance and memories, the batch generators - never leaves: it is kept in memory and
written after every message to ``<state-dir>/run-<Flower run id>/client-<k>.ckpt``, so a
robot whose service or SuperNode is restarted rejoins with it. Only the shared tensors
leave (``ClientSide.upload`` checks them against the scope's keys).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import yaml

from fedlgr.config import ExperimentConfig, check_data, config_from_data, to_yaml
from fedlgr.deploy.flower import wire
from fedlgr.deploy.flower.service import state_dir
from fedlgr.errors import FedlgrError

_robots: dict[tuple[int, int], Robot] = {}  # (Flower run id, client): while the service lives
SERVER = "the server's config"
WEIGHTS = ("none", "imagenet")  # model.weights values that name no file


def node_setting(node_config: dict, key: str, default=None):
    value = node_config.get(key, default)
    if value is None:
        raise FedlgrError(
            f"SuperNode --node-config lacks {key!r}: start it with "
            "--node-config 'data-path=\"/path/to/data\" client=0'"
        )
    return value


class Robot:
    """One robot's client between messages: built once per process, state on disk."""

    def __init__(self, config: ExperimentConfig, client: int, folder: Path):
        import torch
        from lightning.fabric import seed_everything

        from fedlgr.data.dataset import load_scenes
        from fedlgr.data.splits import make_split
        from fedlgr.federated.client_side import ClientSide
        from fedlgr.federated.experiment import make_fabric
        from fedlgr.federated.orchestrator import torch_threads

        if not 0 <= client < config.data.clients:
            raise FedlgrError(
                f"--node-config client={client}: the run has data.clients="
                f"{config.data.clients} (clients 0 to {config.data.clients - 1})"
            )
        fabric = make_fabric(config)
        if fabric.device.type == "cpu":
            torch.set_num_threads(torch_threads(config, 1))
        seed_everything(config.seed, verbose=False)
        scenes = load_scenes(config.data)
        split = make_split(scenes.table, config.data)
        self.side = ClientSide(config, scenes, split, [client], fabric.device, fabric.autocast)
        self.client = self.side.clients[0]
        self.path = folder / f"client-{client}.ckpt"
        self.started, self.ended = -1, -1  # the last task begun and ended
        if self.path.is_file():
            from fedlgr.tracking import checkpoint as ckpt

            state = ckpt.load(self.path)
            self.side.load_state_dict(ckpt.to_device({client: state["client"]}, fabric.device))
            self.started, self.ended = state["started"], state["ended"]
            print(f"client {client}: private state restored from {self.path}", flush=True)

    def save(self) -> None:
        from fedlgr.tracking import checkpoint as ckpt

        state = ckpt.to_device(self.client.state_dict(), "cpu")
        ckpt.write(self.path, {"client": state, "started": self.started, "ended": self.ended})

    def train(self, ins):
        """The round's training; a robot that missed a task's last round ends that task
        first, and one that missed a task's first round begins it here."""
        plan = ins.plan
        for task in range(self.ended + 1, plan.task):
            if self.started >= task:
                self.client.task = self.side.tasks[task]
                self.side.end_task(self.client, plan.round, task)
                self.ended = task
        if self.started < plan.task and not plan.first_of_task:
            ins = dataclasses.replace(ins, plan=dataclasses.replace(plan, first_of_task=True))
        [res] = self.side.train(ins)
        self.started = plan.task
        self.save()
        return res

    def evaluate(self, ins):
        [res] = self.side.evaluate(ins)
        if ins.plan.last_of_task:
            self.ended = ins.plan.task
        self.save()
        return res


def robot(run_id: int, node_config: dict, config_yaml: str) -> Robot:
    """This node's robot for the message's run (built on the run's first message)."""
    client = int(node_setting(node_config, "client"))
    key = (run_id, client)
    if key not in _robots:
        config = robot_config(node_config, config_yaml)
        folder = state_dir(node_config) / f"run-{run_id}"
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "config.yaml").write_text(to_yaml(config))  # what this robot runs
        _robots[key] = Robot(config, client, folder)
    return _robots[key]


class _DataLoader(yaml.SafeLoader):
    """YAML as plain data, without aliases (a few lines of them expand to gigabytes)."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            raise yaml.YAMLError("an alias (*name): not accepted")
        return super().compose_node(parent, index)


def robot_config(node_config: dict, config_yaml: str) -> ExperimentConfig:
    """The run's config on this robot: the server's settings read as data - no
    interpolation, no ``includes`` - with every setting that chooses where the robot
    reads or writes taken from its SuperNode (or the robot's default), never the
    server's: ``data.path``, ``data.cache_dir``, a ``model.weights`` file; no tracking."""
    try:
        settings = yaml.load(config_yaml, Loader=_DataLoader)  # a SafeLoader
    except yaml.YAMLError as err:
        raise FedlgrError(f"{SERVER}: not valid YAML ({str(err).splitlines()[0]})") from None
    check_data(settings, SERVER)
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


def handle(kind: str, run_id: int, node_config: dict, content):
    """The reply content to a ``train`` or ``evaluate`` message's content."""
    if kind == "train":
        ins, config_yaml = wire.decode_train_ins(content)
        return wire.encode_train_res(robot(run_id, node_config, config_yaml).train(ins))
    if kind == "evaluate":
        ins, config_yaml = wire.decode_evaluate_ins(content)
        return wire.encode_evaluate_res(robot(run_id, node_config, config_yaml).evaluate(ins))
    raise FedlgrError(f"unknown message type {kind!r} (fedlgr answers train and evaluate)")
