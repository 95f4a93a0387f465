"""The robot's socket (:mod:`.service`): where it is, and how a message travels on it - a JSON
header and Flower's own protobuf encoding of its content, nothing pickled. Both ends read it: the
ClientApp's side and the robot's (:mod:`.robot`)."""

from __future__ import annotations

import hashlib
import json
import socket
import struct
import tempfile
from pathlib import Path

DEFAULT_STATE_DIR = Path.home() / ".fedlgr" / "node-state"


def state_dir(node_config: dict) -> Path:
    return Path(str(node_config.get("state-dir", DEFAULT_STATE_DIR))).expanduser().absolute()


def socket_path(folder: Path) -> Path:
    """``folder/robot.sock``, or a short path under the temp folder when that is longer
    than a Unix socket address may be."""
    path = folder / "robot.sock"
    if len(str(path)) < 100:
        return path
    digest = hashlib.sha256(str(folder).encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / f"fedlgr-robot-{digest}.sock"


def _send(conn: socket.socket, header: dict, payload: bytes) -> None:
    head = json.dumps(header).encode()
    conn.sendall(struct.pack("!IQ", len(head), len(payload)) + head + payload)


def _receive(conn: socket.socket) -> tuple[dict, bytes]:
    sizes = _exactly(conn, struct.calcsize("!IQ"))
    head_size, payload_size = struct.unpack("!IQ", sizes)
    header = json.loads(_exactly(conn, head_size))
    return header, _exactly(conn, payload_size)


def _exactly(conn: socket.socket, n: int) -> bytes:
    parts, left = [], n
    while left:
        chunk = conn.recv(min(left, 1 << 20))
        if not chunk:
            raise ConnectionError("the robot service closed the connection")
        parts.append(chunk)
        left -= len(chunk)
    return b"".join(parts)


def encode(content) -> bytes:
    from flwr.common.serde import recorddict_to_proto  # lazy: flwr and protobuf, slow to import

    return recorddict_to_proto(content).SerializeToString()


def decode(data: bytes):
    # lazy: flwr and protobuf, slow to import
    from flwr.common.serde import recorddict_from_proto
    from flwr.proto.recorddict_pb2 import RecordDict as ProtoRecordDict

    return recorddict_from_proto(ProtoRecordDict.FromString(data))
