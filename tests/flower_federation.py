"""A real Flower federation on localhost for the tests: a SuperLink with TLS and SuperNode
authentication, SuperNodes (one per robot) and ``flwr run`` - real processes on free
ports, certificates and keys made here, everything stopped at the end."""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from fedlgr.deploy.credentials import make_certificates, make_node_key
from fedlgr.deploy.flower import APP_DIR

BIN = Path(sys.executable).parent  # flower-superlink starts flower-superexec from PATH


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.2)
    raise TimeoutError(f"nothing listens on port {port} after {timeout} s")


class Federation:
    def __init__(self, folder: Path):
        self.folder = folder
        self.creds = folder / "creds"
        make_certificates(self.creds)
        self.home = folder / "flwr-home"  # the flwr CLI's config, not the user's ~/.flwr
        self.home.mkdir(parents=True)
        self.logs = folder / "logs"
        self.logs.mkdir()
        self.port = free_port()
        (self.home / "config.toml").write_text(
            '[superlink]\ndefault = "local"\n\n[superlink.local]\n'
            f'address = "127.0.0.1:{self.port}"\n'
            f'root-certificates = "{self.creds / "ca.pem"}"\n'
        )
        self.env = {
            **os.environ,
            "FLWR_HOME": str(self.home),
            "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
            "PYTHONUNBUFFERED": "1",
            "FLWR_TELEMETRY_ENABLED": "0",
        }
        self.procs: dict[str, subprocess.Popen] = {}

    def spawn(self, name: str, cmd: list[str]) -> subprocess.Popen:
        log = (self.logs / f"{name}.log").open("ab")
        proc = subprocess.Popen(
            cmd,
            stdout=log,
            stderr=subprocess.STDOUT,
            env=self.env,
            cwd=self.folder,
            start_new_session=True,  # its own process group: its apps are stopped with it
        )
        self.procs[name] = proc
        return proc

    def log(self, name: str) -> str:
        return (self.logs / f"{name}.log").read_text(errors="replace")

    def start_superlink(self) -> None:
        self.spawn(
            "superlink",
            [
                "flower-superlink",
                "--ssl-ca-certfile",
                str(self.creds / "ca.pem"),
                "--ssl-certfile",
                str(self.creds / "server.pem"),
                "--ssl-keyfile",
                str(self.creds / "server.key"),
                "--enable-supernode-auth",
                "--disable-runtime-dependency-installation",
                "--host",
                "127.0.0.1",
                "--port",
                str(self.port),
            ],
        )
        wait_port(self.port)

    def flwr(self, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
        return subprocess.run(
            ["flwr", *args],
            env=self.env,
            cwd=self.folder,
            capture_output=True,
            text=True,
            timeout=timeout,
        )

    def node_key(self, name: str, register: bool = True) -> Path:
        private, public = make_node_key(self.creds, name)
        if register:
            out = self.flwr("supernode", "register", str(public), "--format", "json")
            assert out.returncode == 0, out.stdout + out.stderr
            assert json.loads(out.stdout[out.stdout.index("{") :])["success"]
        return private

    def start_supernode(
        self, name: str, key: Path, client: int, data: Path, extra: list[str] = ()
    ) -> subprocess.Popen:
        node_config = (
            f'data-path="{data}" client={client} '
            f'state-dir="{self.folder / "robots" / name}" '
            f'cache-dir="{self.folder / "robots" / name / "cache"}"'
        )
        return self.spawn(
            name,
            [
                "flower-supernode",
                "--superlink",
                f"127.0.0.1:{self.port}",
                "--root-certificates",
                str(self.creds / "ca.pem"),
                "--auth-supernode-private-key",
                str(key),
                "--node-config",
                node_config,
                "--host",
                "127.0.0.1",
                "--port",
                str(free_port()),
                *extra,
            ],
        )

    def run(self, config: Path, overrides: list[str], timeout: float = 600):
        """``flwr run`` of fedlgr's app (streaming its logs until the ServerApp ends)."""
        run_config = f'config="{config}" overrides="{shlex.join(overrides)}"'
        cmd = ["flwr", "run", str(APP_DIR), "local", "--stream", "--run-config", run_config]
        return subprocess.Popen(
            cmd,
            env=self.env,
            cwd=self.folder,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
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
        for pid in self.leftovers():
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)

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
