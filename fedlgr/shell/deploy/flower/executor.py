"""A warm SuperExec: Flower's own task loop, each app process forked from this one, which has Flower
and fedlgr's app imported. Flower's factory names no other executor, so ``get_executor`` is
replaced; forking is safe, since before a fork this process only imports (no torch pool, no GPU)."""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import functools
import importlib
import os
import signal
import sys
import threading
import time
import traceback
import warnings
from collections.abc import Callable
from importlib.metadata import entry_points

from fedlgr.shell.tracking.liveness import process_alive

# The tasks this executor runs, and the module each imports before its first fork besides
# Flower's entry point (the app pulls in torch and the rest).
PRELOAD = {
    "clientapp": "fedlgr.shell.deploy.flower.client_app",
    "serverapp": "fedlgr.shell.deploy.flower.server_app",
}


@functools.cache
def entry(command: str) -> Callable[[], object]:
    """The function behind Flower's console script ``command`` (``flwr-clientapp``): what
    the process Flower's SubprocessExecutor starts would run."""
    [script] = entry_points(group="console_scripts", name=command)
    return script.load()


def task_argv(spec) -> list[str]:
    """The command line Flower's ``SubprocessExecutor.launch`` builds for ``spec``."""
    # lazy: flwr (seconds): the executor watches its parent before any slow import
    from flwr.supercore.constant import TASK_TYPE_TO_APPIO_API_ADDRESS_ARG, TASK_TYPE_TO_COMMAND

    argv = [TASK_TYPE_TO_COMMAND[spec.task_type]]
    argv += [TASK_TYPE_TO_APPIO_API_ADDRESS_ARG[spec.task_type], spec.runtime_api_address]
    argv += ["--token", spec.token]
    if spec.insecure:
        argv.append("--insecure")
    elif spec.root_certificates_path is not None:
        argv += ["--root-certificates", spec.root_certificates_path]
    if spec.parent_pid is not None:
        argv += ["--parent-pid", str(spec.parent_pid)]
    if spec.runtime_dependency_install:
        argv.append("--allow-runtime-dependency-installation")
    return argv


class ForkExecutor:
    """A Flower ``Executor`` whose task processes are forks of this process."""

    def __init__(self):
        self.owner = os.getpid()
        self.children: dict[int, object] = {}  # pid -> its task's ExecutionSpec

    def get_eligible_capacity(self, supported_task_types, *, insecure=False, **_):
        return supported_task_types, set()

    def wait_for_capacity(self, task_type=None, **_) -> None:
        """No capacity gate, as Flower's SubprocessExecutor."""

    def launch(self, spec):
        # lazy: flwr (seconds): the executor watches its parent before any slow import
        from flwr.supercore.superexec.executor import LaunchResult

        argv = task_argv(spec)
        if argv[0].removeprefix("flwr-") not in PRELOAD:
            return LaunchResult.failed(
                f"fedlgr's executor runs ClientApps and ServerApps, not {spec.task_type}"
            )
        app = entry(argv[0])
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _run_child(app, argv, spec.suppress_output, self.owner)  # never returns
        self.children[pid] = spec
        return LaunchResult.accepted()

    def reconcile(self) -> None:
        """Reap the task processes that ended (Flower's loop calls this every poll); a ServerApp
        killed outright (SIGKILL, the OOM killer) is reported failed, as its own exit would."""
        for pid, spec in list(self.children.items()):
            try:
                done, status = os.waitpid(pid, os.WNOHANG)
            except ChildProcessError:
                done, status = pid, 0
            if not done:
                continue
            del self.children[pid]
            if os.WIFSIGNALED(status) and task_argv(spec)[0] == "flwr-serverapp":
                _report_killed(spec, signal.Signals(os.WTERMSIG(status)).name)

    def close(self) -> None:
        """Task processes are left to end on their own, as Flower's SubprocessExecutor
        leaves them (each watches this process and leaves when it is gone)."""


def _report_killed(spec, how: str) -> None:
    """Finish the task of a ServerApp killed by signal ``how`` as failed, with its token, as its
    own exit handler would have: the SuperLink would hold its run RUNNING until the task's heartbeat
    lapsed (a minute), and the robots would work on for it until then."""
    # lazy: flwr (seconds): the executor watches its parent before any slow import
    import httpx
    from flwr.common.constant import SubStatus
    from flwr.proto.runtime_pb2 import PushTaskOutputRequest
    from flwr.supercore.interceptors import (
        RuntimeTokenHttpInterceptor,
        RuntimeVersionHttpInterceptor,
    )
    from flwr.supercore.runtime import RuntimeHttpClient
    from flwr.supercore.tls import validate_and_resolve_root_certificates

    client = RuntimeHttpClient.from_server_address(
        server_address=spec.runtime_api_address,
        insecure=spec.insecure,
        root_certificates=validate_and_resolve_root_certificates(
            spec.root_certificates_path, spec.insecure
        ),
        interceptors=[
            RuntimeVersionHttpInterceptor(component_name="flwr-serverapp"),
            RuntimeTokenHttpInterceptor(token=spec.token),
        ],
    )
    details = f"the ServerApp process was killed ({how})"
    try:
        client.PushTaskOutput(PushTaskOutputRequest(sub_status=SubStatus.FAILED, details=details))
        print(f"fedlgr: {details}: its task is reported failed to the SuperLink", flush=True)
    except httpx.HTTPError as err:
        print(f"fedlgr: {details}; the SuperLink was not told: {err}", flush=True)
    finally:
        client.close()


def _run_child(app, argv: list[str], quiet: bool, owner: int) -> None:
    """In the forked task process: Flower's entry point as a fresh process would run it, leaving
    when the executor ``owner`` has gone (Flower's monitor counts an unreaped one as alive)."""
    code = 1
    try:
        # lazy: flwr (seconds): the executor watches its parent before any slow import
        from flwr.supercore.exit import exit_handler

        # The parent's exit handlers (closing its Runtime API client) are not this task's.
        exit_handler.registered_exit_handlers.clear()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGCHLD):
            signal.signal(sig, signal.SIG_DFL)
        leave_with(owner)
        if quiet:  # as SubprocessExecutor's stdout/stderr=DEVNULL
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            os.close(devnull)
        _name(argv[0])
        sys.argv = argv
        app()
        code = 0
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    except BaseException:
        traceback.print_exc()
    finally:
        _flush()
        os._exit(code)


def leave_with(parent_pid: int) -> None:
    """Exit at once (quietly, status 0) when ``parent_pid`` has ended or this process is orphaned:
    Flower's own monitor counts an unreaped parent as alive, and would retry a gone Runtime API for
    ever. ``os._exit``, since the interpreter's exit would wait for Flower's threads."""
    parent = os.getppid()

    def watch() -> None:
        while process_alive(parent_pid) and os.getppid() == parent:
            time.sleep(0.2)
        _flush()
        os._exit(0)

    threading.Thread(target=watch, name="fedlgr-leave-with-parent", daemon=True).start()


def _flush() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()


def _name(name: str) -> None:
    """The process's name (``ps -o comm``, ``pgrep flwr-clientapp``) as Flower's own
    process would have it; its command line stays this executor's."""
    if sys.platform == "linux":
        ctypes.CDLL(None).prctl(15, name.encode()[:15], 0, 0, 0)  # 15: PR_SET_NAME


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fedlgr.shell.deploy.flower.executor")
    parser.add_argument("--runtime-api-address", required=True)
    parser.add_argument("--insecure", action="store_true")
    parser.add_argument("--root-certificates")
    parser.add_argument("--parent-pid", type=int)
    parser.add_argument("--preload", choices=sorted(PRELOAD), action="append", default=[])
    args = parser.parse_args(argv)
    if args.parent_pid is not None:
        leave_with(args.parent_pid)  # before the preload, which takes seconds
    # Python 3.12+ warns at every fork of a process with threads; this one's other threads
    # (Flower's parent-process monitor, leave_with's) hold no lock a task needs.
    warnings.filterwarnings("ignore", "This process .* is multi-threaded", DeprecationWarning)
    for kind in args.preload:
        importlib.import_module(PRELOAD[kind])
        entry(f"flwr-{kind}")
    # lazy: flwr (seconds): the executor watches its parent before any slow import
    from flwr.supercore.superexec import run_superexec as loop

    executor = ForkExecutor()
    # Flower's factory knows only its own executors (see the module's docstring).
    loop.get_executor = lambda *_, **__: executor
    loop.run_superexec(
        runtime_api_address=args.runtime_api_address,
        insecure=args.insecure,
        root_certificates_path=args.root_certificates,
        parent_pid=args.parent_pid,
    )
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        # Stopped by its SuperNode or SuperLink, maybe while still importing: exit at once, since
        # the interpreter's exit would wait for Flower's threads.
        _flush()
        os._exit(130)
