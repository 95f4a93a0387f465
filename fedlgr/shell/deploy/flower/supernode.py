"""``flower-supernode`` with a poll interval a robot chooses (``fedlgr deploy supernode``
execs ``python -m fedlgr.shell.deploy.flower.supernode --poll-s S FLOWER_ARGS``).

flwr 1.42's SuperNode asks the SuperLink for a message, and when none waits it sleeps a
fixed 3 s (``time.sleep(3)`` in ``flwr.supernode.start_client_internal``; no option or
environment variable sets it). A robot that has just answered is in that sleep when the
server sends the next round, so every exchange waited ~2.5 s for nothing (bench/README.md
"Flower rounds": 4 of a 3-round run's 6.4 s exchanges). Having answered, it then waits
for the ClientApp's reply by polling its own state every 0.5 s.

Flower offers no setting for either, so fedlgr reaches into Flower here:
the module's ``time`` is replaced by :class:`_Clock`, whose ``sleep`` shortens those two
waits - the idle poll to ``--poll-s`` seconds (each poll is one small
authenticated request to the SuperLink), the reply wait (a look at the SuperNode's own
memory) to 0.1 s - and passes every other use of ``time`` through.

The same goes for the node's heartbeat: flwr 1.42's SuperNode tells the SuperLink it beats
every 30 s (``HEARTBEAT_DEFAULT_INTERVAL``, read by its REST connection and its heartbeat
sender; no option), and the SuperLink declares a node lost - and refuses its key to a
restarted SuperNode - after two missed intervals, about a minute. ``--heartbeat-s S``
(10 to 1800 s, the range the SuperLink accepts) sets that interval, so a robot that died is
declared lost, and may come back, after ~2 S. ``tests/test_deploy_cli.py`` checks that
flwr still reads these names, so a flwr upgrade that changes them is noticed.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

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
    """``[--poll-s S] [--heartbeat-s S] [--warm-apps HOST:PORT] FLOWER_ARGS``:
    flower-supernode FLOWER_ARGS, its idle poll S seconds (Flower's own waits without
    ``--poll-s``), its heartbeat every S seconds (Flower's 30 without ``--heartbeat-s``), and with
    ``--warm-apps`` its ClientApps forked by :mod:`.executor` from a process that has
    imported them (the SuperNode in Flower's ``process`` isolation, the executor on its
    Runtime API at HOST:PORT). ``fedlgr deploy supernode`` builds and checks the line."""
    # lazy: flwr (seconds); `fedlgr --help` imports this module for its constants
    from flwr.supernode import start_client_internal as internal
    from flwr.supernode.cli import flower_supernode

    args = list(sys.argv[1:] if argv is None else argv)
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
        # Ctrl-C before Flower's own handlers are in place, while the imports above run
        # (over 8 s under load): one line, not their traceback. A warm executor started
        # already leaves by itself (executor.leave_with).
        print("fedlgr: interrupted", file=sys.stderr, flush=True)
        os._exit(130)  # the interpreter's exit could wait for threads Flower started
