"""The robot service: one long-lived process per robot (Flower starts one per message) that loads
torch and the data once and answers over a Unix socket (mode 0600): a JSON header and Flower's
protobuf encoding of the content, nothing pickled. It leaves after ``robot-idle-s`` idle seconds,
and once its SuperNode has ended (~1 GB of memory that no ClientApp will ask again)."""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path

from filelock import FileLock

from fedlgr.shell.deploy.flower.link import SUPERNODE_PID, decode, encode, state_dir
from fedlgr.shell.tracking.liveness import process_alive, process_started

DEFAULT_IDLE_S = 900.0
START_TIMEOUT_S = 300.0  # the service's first start imports torch and loads the data
WATCH_S = 1.0  # how often the service looks whether its SuperNode is still there


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
    with conn.makefile("rb") as stream:
        head_size, payload_size = struct.unpack("!IQ", _exactly(stream, struct.calcsize("!IQ")))
        return json.loads(_exactly(stream, head_size)), _exactly(stream, payload_size)


def _exactly(stream, n: int) -> bytes:
    data = stream.read(n)
    if len(data) < n:
        raise ConnectionError("the robot service closed the connection")
    return data


# ---------------------------------------------------------------------- ClientApp side


def ask(kind: str, run_id: int, node_config: dict, content):
    """The robot service's reply content to one message (starting the service if none
    answers). A failure on the robot raises ``RuntimeError`` with its message."""
    folder = state_dir(node_config)
    path = socket_path(folder)
    header = {"kind": kind, "run_id": int(run_id), "node_config": dict(node_config)}
    payload = encode(content)
    try:
        conn = _connect(path)
    except OSError:
        start(folder, node_config)
        conn = _connect(path, wait=START_TIMEOUT_S)
    with conn:
        _send(conn, header, payload)
        reply, data = _receive(conn)
    if not reply.get("ok"):
        raise RuntimeError(reply.get("error", "the robot service failed"))
    return decode(data)


def _connect(path: Path, wait: float = 0.0) -> socket.socket:
    deadline = time.monotonic() + wait
    while True:
        conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            conn.connect(str(path))
            return conn
        except OSError:
            conn.close()
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.2)


def start(folder: Path, node_config: dict) -> None:
    """Start the service for ``folder`` unless another ClientApp is starting it."""
    folder.mkdir(parents=True, exist_ok=True)
    with FileLock(folder / "robot.lock", fallback_to_soft=False):  # released if it is killed
        with contextlib.suppress(OSError):
            _connect(socket_path(folder)).close()
            return  # started meanwhile
        idle = str(float(node_config.get("robot-idle-s", DEFAULT_IDLE_S)))
        supernode = os.environ.get(SUPERNODE_PID, "")  # set by fedlgr's SuperNode (supernode.py)
        log = (folder / "robot.log").open("ab")
        module = "fedlgr.shell.deploy.flower.service"
        subprocess.Popen(
            [sys.executable, "-m", module, str(folder), idle, supernode],
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,  # outlives this ClientApp process
        )
        _connect(socket_path(folder), wait=START_TIMEOUT_S).close()


# ---------------------------------------------------------------------- the service


def serve(folder: Path, idle_s: float = DEFAULT_IDLE_S, supernode: int | None = None) -> None:
    """Answer messages on ``folder``'s socket until ``idle_s`` seconds pass without one, or the
    process ``supernode`` (the SuperNode whose ClientApp started this service) has ended."""
    started = process_started(supernode) if supernode is not None else ""
    from fedlgr.shell.deploy.flower.robot import handle  # lazy: torch, in the service only

    path = socket_path(folder)
    path.unlink(missing_ok=True)
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    old = os.umask(0o177)  # the socket is this user's only
    try:
        server.bind(str(path))
    finally:
        os.umask(old)
    server.listen()
    server.settimeout(idle_s)
    (folder / "robot.pid").write_text(str(os.getpid()))
    # SIGTERM and the SuperNode's end leave through the finally below, even in the middle of a
    # message: no stale robot.pid or robot.sock.
    signal.signal(signal.SIGTERM, functools.partial(_leave, "SIGTERM"))
    print(f"robot service {os.getpid()} listening on {path}", flush=True)
    try:
        if supernode is not None:
            _leave_with(supernode, started)
        while True:
            try:
                conn, _ = server.accept()
            except TimeoutError:
                print(f"no message for {idle_s:g} s: leaving", flush=True)
                return
            with conn:
                try:
                    _answer(conn, handle)
                except OSError as err:  # the ClientApp went away (its SuperNode was killed)
                    print(f"could not answer: {err}", flush=True)
    except _Stopped as stop:
        print(f"{stop}: leaving", flush=True)
    finally:
        server.close()
        path.unlink(missing_ok=True)
        (folder / "robot.pid").unlink(missing_ok=True)


class _Stopped(BaseException):
    """SIGTERM, or the SuperNode's end: the service leaves (a BaseException, since a robot's own
    failure, an Exception, is answered and the service goes on)."""


def _leave(why: str, signum, frame) -> None:
    raise _Stopped(why)


def _leave_with(supernode: int, started: str) -> None:
    """Leave (SIGUSR1: :class:`_Stopped`) within :data:`WATCH_S` of the end of the process
    ``supernode``, even in the middle of a message: its ClientApps, the only ones to ask this
    service and to read its replies, ended with it."""
    why = f"SuperNode {supernode} has ended"
    signal.signal(signal.SIGUSR1, functools.partial(_leave, why))

    def watch() -> None:
        while process_alive(supernode, started):
            time.sleep(WATCH_S)
        os.kill(os.getpid(), signal.SIGUSR1)

    threading.Thread(target=watch, name="fedlgr-leave-with-supernode", daemon=True).start()


def _answer(conn: socket.socket, handle) -> None:
    conn.settimeout(None)
    if not conn.recv(1, socket.MSG_PEEK):  # closed before a byte: start() checking we listen
        return
    header, payload = _receive(conn)
    print(f"run {header['run_id']}: {header['kind']} received", flush=True)
    started = time.perf_counter()
    try:
        reply = handle(header["kind"], header["run_id"], header["node_config"], decode(payload))
    except Exception as err:  # the robot's failure goes back to the server as the reply
        traceback.print_exc()
        _send(conn, {"ok": False, "error": reply_error(err)}, b"")
        return
    _send(conn, {"ok": True}, reply)
    seconds = time.perf_counter() - started
    print(f"run {header['run_id']}: {header['kind']} answered in {seconds:.1f} s", flush=True)


def reply_error(err: Exception) -> str:
    """What the server is told of a failure: its first line, at most 1000 characters (the
    whole text and the traceback stay in the robot's log)."""
    lines = str(err).strip().splitlines()
    return f"{type(err).__name__}: {lines[0][:1000] if lines else 'no message'}"


if __name__ == "__main__":  # FOLDER IDLE_S [SUPERNODE_PID]
    supernode = sys.argv[3] if len(sys.argv) > 3 else ""
    serve(Path(sys.argv[1]), float(sys.argv[2]), int(supernode) if supernode else None)
