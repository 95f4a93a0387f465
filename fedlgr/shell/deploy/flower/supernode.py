"""``flower-supernode`` with shorter waits (``fedlgr deploy supernode`` execs it): flwr sleeps 3 s
when idle and 0.5 s between looks for a reply, with no option, so :class:`_Clock` replaces time;
and a ClientApp whose run has ended is stopped (:class:`_RunWatch`)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable

from fedlgr.shell.deploy.flower.link import SUPERNODE_PID

FLOWER_IDLE_S = 3.0  # flwr's sleep when the SuperLink had no message
REPLY_WAIT_S = 0.1  # our wait between looks for the ClientApp's reply (flwr: 0.5 s)
RUN_CHECK_S = 2.0  # while a ClientApp answers, how often its run's status is asked for
STOP_WAIT_S = 5.0  # for a stopped ClientApp's own exit (flwr's), before SIGKILL
POLL_RANGE = (0.05, 3.0)
HEARTBEAT_RANGE = (10.0, 1800.0)  # what flwr's SuperLink accepts (HEARTBEAT_MIN/MAX_INTERVAL)


class _Clock:
    """``time`` for ``start_client_internal``, with its waits shortened; each of its waits for a
    ClientApp's reply (flwr's sleeps under 3 s) calls ``waiting`` first, which may end it."""

    def __init__(self, poll_s: float, waiting: Callable[[], None]):
        self.poll_s, self.waiting = poll_s, waiting

    def sleep(self, seconds: float) -> None:
        if seconds >= FLOWER_IDLE_S:
            time.sleep(self.poll_s)
            return
        self.waiting()
        time.sleep(min(seconds, REPLY_WAIT_S))

    def __getattr__(self, name: str):
        return getattr(time, name)


class _RunEnded(BaseException):
    """The run of the message being answered is no longer running (flwr's own
    ``RunNotRunningException`` is a BaseException too: no handler of flwr's takes it)."""


class _RunWatch:
    """Stops a ClientApp whose run has ended. flwr's SuperNode waits for a ClientApp's reply however
    long it takes - a robot's training, minutes - though the run's ServerApp has gone meanwhile
    (killed, stopped): the ClientApp stayed, waiting on the robot service. While it waits, the run
    is looked up on the SuperLink every :data:`RUN_CHECK_S`; once it is no longer running, the
    ClientApp is stopped (SIGTERM: flwr's own exit) and the run's message dropped, so the next
    run's messages are taken. flwr's loop calls these functions by their module names."""

    def __init__(self, internal):
        self.flower = (
            internal._init_connection,
            internal._pull_and_store_message,
            internal._push_messages,
        )
        internal._init_connection = self.connection
        internal._pull_and_store_message = self.pull
        internal._push_messages = self.push
        self.get_run = None  # the Fleet API's GetRun, once connected
        self.run_id: int | None = None  # the run of the message being answered
        self.answering = False  # flwr waits for the ClientApp's reply
        self.checked = 0.0  # when the run was last looked up

    @contextlib.contextmanager
    def connection(self, *args, **kwargs):
        with self.flower[0](*args, **kwargs) as conn:
            self.get_run = conn[3]  # (node id, receive, send, get_run, get_fab, ...)
            yield conn

    def pull(self, **kwargs) -> int | None:
        self.run_id = self.flower[1](**kwargs)
        return self.run_id

    def push(self, **kwargs) -> None:
        self.answering, self.checked = True, time.monotonic()
        try:
            self.flower[2](**kwargs)
        except _RunEnded:
            self._drop(kwargs["state"], kwargs["object_store"])
        finally:
            self.answering = False

    def waiting(self) -> None:
        """While flwr waits for the ClientApp's reply: every :data:`RUN_CHECK_S`, whether its run
        still runs; :class:`_RunEnded` once it does not."""
        if not self.answering or time.monotonic() - self.checked < RUN_CHECK_S:
            return
        self.checked = time.monotonic()
        if not self._running():
            raise _RunEnded

    def _running(self) -> bool:
        import httpx  # lazy: with flwr, already loaded here
        from flwr.supercore.run import RunNotRunningException  # lazy: as above

        try:
            self.get_run(self.run_id)  # the SuperLink refuses a run that is not running
        except RunNotRunningException:
            return False
        except httpx.HTTPError as err:  # not a reason to stop a robot's work
            print(f"fedlgr: run {self.run_id}'s status: {err}", flush=True)
        return True

    def _drop(self, state, object_store) -> None:
        stopped = _stop_clientapps()
        ids = [m.metadata.message_id for m in state.get_messages_legacy(run_ids=[self.run_id])]
        state.delete_messages(message_ids=ids)
        object_store.delete_objects_in_run(self.run_id)
        print(
            f"fedlgr: run {self.run_id} is no longer running on the SuperLink: "
            f"{stopped} ClientApp process(es) stopped, its message dropped",
            flush=True,
        )


def _stop_clientapps() -> int:
    """Stop this SuperNode's ClientApp processes (its SuperExec's children), waiting for them to
    end; how many there were."""
    import psutil  # lazy: psutil, only when a run has ended under a ClientApp

    apps = []
    for child in psutil.Process().children(recursive=True):
        with contextlib.suppress(psutil.Error):
            if child.name() == "flwr-clientapp":
                child.send_signal(signal.SIGTERM)
                apps.append(child)
    _, alive = psutil.wait_procs(apps, timeout=STOP_WAIT_S)
    for child in alive:
        with contextlib.suppress(psutil.Error):
            child.kill()
    return len(apps)


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
    poll_s = FLOWER_IDLE_S
    if args[:1] == ["--poll-s"]:
        poll_s = float(args[1])
        del args[:2]
    internal.time = _Clock(poll_s, _RunWatch(internal).waiting)
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
