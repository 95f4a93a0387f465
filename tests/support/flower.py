"""A real Flower federation on localhost for the tests: a SuperLink with TLS and SuperNode
authentication, SuperNodes (one per robot) and ``flwr run`` - real processes on free
ports, certificates and keys made here, everything stopped at the end."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from .ports import free_port, wait_port

BIN = Path(sys.executable).parent  # flower-superlink starts flower-superexec from PATH


class Federation:
    """Started with the commands docs/deployment.md gives (``fedlgr deploy ...``)."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.creds = folder / "creds"
        self.home = folder / "flwr-home"  # the flwr CLI's config, not the user's ~/.flwr
        self.home.mkdir(parents=True)
        self.logs = folder / "logs"
        self.logs.mkdir()
        self.port = free_port()
        self.env = {
            **os.environ,
            "FLWR_HOME": str(self.home),
            "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
            "PYTHONUNBUFFERED": "1",
            "FLWR_SUPEREXEC_TASK_POLL_INTERVAL": "0.2",  # Flower's default: 1 s
        }
        self.procs: dict[str, subprocess.Popen] = {}
        self.starts: dict[str, int] = {}  # where each log's latest start begins
        self.fedlgr("certs", str(self.creds))
        ca = str(self.creds / "ca.pem")
        self.fedlgr("connect", "local", "--superlink", f"127.0.0.1:{self.port}", "--ca", ca)

    def fedlgr(self, *args: str) -> subprocess.CompletedProcess:
        out = subprocess.run(
            [str(BIN / "fedlgr"), "deploy", *args],
            env=self.env,
            cwd=self.folder,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert out.returncode == 0, out.stdout + out.stderr
        return out

    def spawn(
        self, name: str, cmd: list[str], env: dict[str, str] | None = None
    ) -> subprocess.Popen:
        """``env``: what this process alone has in its environment besides ``self.env``."""
        log = (self.logs / f"{name}.log").open("ab")
        self.starts[name] = log.tell()
        proc = subprocess.Popen(
            cmd,
            stdout=log,
            stderr=subprocess.STDOUT,
            env={**self.env, **(env or {})},
            cwd=self.folder,
        )
        self.procs[name] = proc
        return proc

    def log(self, name: str) -> str:
        """What the latest start of ``name`` has logged (a restarted SuperNode appends to
        the same file: an earlier start's lines are not this one's)."""
        whole = (self.logs / f"{name}.log").read_bytes()
        return whole[self.starts.get(name, 0) :].decode(errors="replace")

    def start_superlink(self, extra: list[str] = (), env: dict[str, str] | None = None) -> None:
        """``fedlgr deploy superlink``: SuperNodes use the gateway on ``self.port``, ``flwr``
        (connection ``local``) Flower's own port on loopback, ``self.internal_port``;
        ``env``: the SuperLink machine's own environment (the other processes lack it)."""
        self.internal_port = free_port()
        link = ["superlink", "--certs", str(self.creds), "--host", "127.0.0.1", *extra]
        link += ["--port", str(self.port), "--internal-port", str(self.internal_port)]
        self.spawn("superlink", [str(BIN / "fedlgr"), "deploy", *link], env)
        wait_port(self.port)  # the gateway listens once Flower does
        ca = str(self.creds / "ca.pem")
        local = f"127.0.0.1:{self.internal_port}"
        self.fedlgr("connect", "local", "--superlink", local, "--ca", ca)

    @property
    def roster(self) -> Path:
        return self.creds / "roster.yaml"  # fedlgr deploy node-key adds each robot to it

    def node_key(self, name: str, register: bool = True, roster: bool = True) -> Path:
        self.fedlgr("node-key", str(self.creds), name, *(() if roster else ("--no-roster",)))
        if register:
            out = subprocess.run(
                ["flwr", "supernode", "register", str(self.creds / f"{name}.pub")],
                env=self.env,
                capture_output=True,
                text=True,
                timeout=120,
            )
            assert out.returncode == 0, out.stdout + out.stderr
        return self.creds / name

    def robot_dir(self, name: str) -> Path:
        return self.folder / "robots" / name

    def start_supernode(
        self,
        name: str,
        key: Path,
        client: int | None,
        data: Path,
        extra: list[str] = (),
        env: dict | None = None,
        port: int | None = None,
    ) -> subprocess.Popen:
        """``client``: the slot the robot expects (``--client``); None: the roster's;
        ``env``: added to its environment (and its ClientApps' and robot service's);
        ``port``: where it reaches the SuperLink (default: the robots' port)."""
        robot = self.robot_dir(name)
        node = ["supernode", "--superlink", f"127.0.0.1:{port or self.port}"]
        node += ["--ca", str(self.creds / "ca.pem"), "--key", str(key), "--data", str(data)]
        node += [*(() if client is None else ("--client", str(client))), "--state-dir", str(robot)]
        node += ["--cache-dir", str(robot / "cache"), "--port", str(free_port())]
        # Flower's shortest heartbeat: a killed robot is declared lost (and its key taken
        # back) after ~20 s, not ~1 min
        node += ["--heartbeat-s", "10"]
        return self.spawn(name, [str(BIN / "fedlgr"), "deploy", *node, *extra], env)

    def run(self, config: Path, overrides: list[str], stderr=subprocess.STDOUT) -> subprocess.Popen:
        """``fedlgr deploy run``: flwr run of fedlgr's app, its log streamed to stdout (and its
        errors, unless ``stderr`` says otherwise)."""
        cmd = [str(BIN / "fedlgr"), "deploy", "run", str(config), *overrides]
        return subprocess.Popen(
            [*cmd, "--federation", "local"],
            env=self.env,
            cwd=self.folder,
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
        )

    def stop(self) -> None:
        """SIGTERM to every process, then SIGKILL to whatever of this federation is left
        (Flower starts its SuperExec and app processes in sessions of their own: they are
        found by this federation's FLWR_HOME in their environment)."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.terminate()
        deadline = time.monotonic() + 15
        for proc in self.procs.values():
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        time.sleep(1)  # SuperExecs leave on their own once their parent is gone
        # What is left (robot services, a killed SuperNode's ClientApp) carries FLWR_HOME.
        for pid in self.leftovers():
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 15  # a signal is delivered, not waited for
        while self.leftovers() and time.monotonic() < deadline:
            time.sleep(0.2)

    def leftovers(self) -> list[int]:
        """Live processes started for this federation."""
        needle = f"FLWR_HOME={self.home}".encode()
        found = []
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit() or int(entry.name) == os.getpid():
                continue
            with contextlib.suppress(OSError):
                if needle in (entry / "environ").read_bytes().split(b"\0"):
                    found.append(int(entry.name))
        return found
