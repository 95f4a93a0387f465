"""``flower-supernode`` with shorter waits (``fedlgr deploy supernode`` execs it): flwr sleeps 3 s
when idle and 0.5 s between looks for a reply, with no option, so :class:`_Clock` replaces time."""

from __future__ import annotations

import os
import subprocess
import sys
import time

from fedlgr.shell.deploy.flower.link import SUPERNODE_PID

FLOWER_IDLE_S = 3.0  # flwr's sleep when the SuperLink had no message
REPLY_WAIT_S = 0.1  # our wait between looks for the ClientApp's reply (flwr: 0.5 s)
POLL_RANGE = (0.05, 3.0)
HEARTBEAT_RANGE = (10.0, 1800.0)  # what flwr's SuperLink accepts (HEARTBEAT_MIN/MAX_INTERVAL)


class _Clock:
    """``time`` for ``start_client_internal``, with its waits shortened."""

    def __init__(self, poll_s: float):
        self.poll_s = poll_s

    def sleep(self, seconds: float) -> None:
        time.sleep(self.poll_s if seconds >= FLOWER_IDLE_S else min(seconds, REPLY_WAIT_S))

    def __getattr__(self, name: str):
        return getattr(time, name)


def set_heartbeat(seconds: float) -> None:
    """The heartbeat interval this SuperNode declares to the SuperLink and beats at."""
    # lazy: flwr (seconds); `fedlgr --help` imports this module for its constants
    from flwr.supercore import heartbeat
    from flwr.supernode import fleet_http_connection

    for module in (fleet_http_connection, heartbeat):
        module.HEARTBEAT_DEFAULT_INTERVAL = seconds


def main(argv: list[str] | None = None) -> int:
    """``[--poll-s S] [--heartbeat-s S] [--warm-apps HOST:PORT] FLOWER_ARGS``: flower-supernode
    FLOWER_ARGS with its idle poll and heartbeat set, and with ``--warm-apps`` its ClientApps forked
    by :mod:`.executor` (on the Runtime API at HOST:PORT) from a process that has imported them."""
    # lazy: flwr (seconds); `fedlgr --help` imports this module for its constants
    from flwr.supernode import start_client_internal as internal
    from flwr.supernode.cli import flower_supernode

    args = list(sys.argv[1:] if argv is None else argv)
    os.environ[SUPERNODE_PID] = str(os.getpid())  # its ClientApps' robot service watches it
    if args[:1] == ["--poll-s"]:
        internal.time = _Clock(float(args[1]))
        del args[:2]
    if args[:1] == ["--heartbeat-s"]:
        set_heartbeat(float(args[1]))
        del args[:2]
    if args[:1] == ["--warm-apps"]:
        executor = [sys.executable, "-m", "fedlgr.shell.deploy.flower.executor", "--preload"]
        executor += ["clientapp", "--runtime-api-address", args[1], "--insecure"]
        # Flower's SuperExec for this SuperNode, bar the executor: it leaves when we do.
        subprocess.Popen([*executor, "--parent-pid", str(os.getpid())])
        args = [*args[2:], "--isolation", "process"]
    sys.argv = ["flower-supernode", *args]
    return flower_supernode() or 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        # Ctrl-C while the imports above run, before Flower's handlers: one line, not a traceback.
        print("fedlgr: interrupted", file=sys.stderr, flush=True)
        os._exit(130)  # the interpreter's exit could wait for threads Flower started
