"""Free localhost ports, and waiting for one to listen (or an HTTP server to answer)."""

from __future__ import annotations

import socket
import subprocess
import time
import urllib.request
from collections.abc import Callable

import pytest


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


def wait_healthy(
    url: str, process: subprocess.Popen, why_dead: Callable[[], str], timeout: float
) -> None:
    """Until the HTTP server at ``url`` (an ``mlflow server``) answers ``/health`` with 200;
    the test fails with ``why_dead()`` (its log) if ``process`` ends first."""
    deadline = time.monotonic() + timeout
    while True:
        if process.poll() is not None:
            pytest.fail(f"{url}: the server exited: {why_dead()}")
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=2) as answer:
                if answer.status == 200:
                    return
        except OSError:
            pass
        if time.monotonic() > deadline:
            pytest.fail(f"{url}: no /health answer within {timeout:g} s")
        time.sleep(0.5)
