"""What both ends of the robot's socket read (the ClientApp's side, :mod:`.service`, and the
robot's, :mod:`.robot`): where a robot keeps its state, and how a message's content is
encoded - Flower's own protobuf encoding, nothing pickled."""

from __future__ import annotations

from pathlib import Path

DEFAULT_STATE_DIR = Path.home() / ".fedlgr" / "node-state"
# The SuperNode's pid, in the environment of its ClientApps: the robot service one of them starts
# leaves when that SuperNode has ended.
SUPERNODE_PID = "FEDLGR_SUPERNODE_PID"


def state_dir(node_config: dict) -> Path:
    return Path(str(node_config.get("state-dir", DEFAULT_STATE_DIR))).expanduser().absolute()


def encode(content) -> bytes:
    from flwr.common.serde import recorddict_to_proto  # lazy: flwr and protobuf, slow to import

    return recorddict_to_proto(content).SerializeToString()


def decode(data: bytes):
    # lazy: flwr and protobuf, slow to import
    from flwr.common.serde import recorddict_from_proto
    from flwr.proto.recorddict_pb2 import RecordDict as ProtoRecordDict

    return recorddict_from_proto(ProtoRecordDict.FromString(data))
