"""The robots' port of ``fedlgr deploy superlink``: forwards Flower's Fleet API (POSTs to
``/v1/fleet/...``) to a SuperLink bound to 127.0.0.1 and refuses all else (403), since Flower serves
its Control API, which has no login and runs code on the server, on the same port."""

from __future__ import annotations

import asyncio
import ctypes
import ipaddress
import re
import signal
import socket
import ssl
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import uvicorn
from cryptography import x509
from starlette.background import BackgroundTask
from starlette.requests import ClientDisconnect, Request
from starlette.responses import PlainTextResponse, Response, StreamingResponse

from fedlgr.errors import FedlgrError
from fedlgr.shell.signals import deferred

# One name of Flower's Fleet router (``flwr/superlink/routers/fleet/router.py``): no '.',
# '/' or '%' can follow, so no path forwarded resolves outside ``/v1/fleet/``.
FLEET_PATH = re.compile(r"/v1/fleet/[a-z0-9]+(?:-[a-z0-9]+)*")
HOP_BY_HOP = frozenset(
    {
        b"connection",
        b"keep-alive",
        b"proxy-authenticate",
        b"proxy-authorization",
        b"proxy-connection",
        b"te",
        b"trailer",
        b"trailers",
        b"transfer-encoding",
        b"upgrade",
        b"host",  # the SuperLink's own, set by httpx
    }
)
UPSTREAM_TIMEOUT_S = 300.0  # above the SuperNode's own 30 s per request
EXECUTOR = "fedlgr.shell.deploy.flower.executor"  # the module of the executor's command
READY_TIMEOUT_S = 300.0  # flower-superlink takes seconds to listen
STOP_GRACE_S = 15.0  # its shutdown stops its SuperExec and a run's ServerApp


@dataclass(frozen=True)
class Tls:
    """The deployment's files (``fedlgr deploy certs``): the gateway serves with
    ``cert``/``key`` and checks the loopback SuperLink's certificate against ``ca``."""

    ca: Path
    cert: Path
    key: Path


def refusal(internal: str) -> str:
    """The one-line body of every 403."""
    return (
        "fedlgr gateway: this port serves SuperNodes only (the Fleet API, POST /v1/fleet/...); "
        "the Control API (flwr run, flwr supernode register) is served only on the "
        f"SuperLink's machine, at {internal}\n"
    )


def covers_loopback(cert: Path) -> bool:
    """Whether the server certificate names 127.0.0.1, where the gateway (and Flower's own
    SuperExec) reach the SuperLink."""
    server = x509.load_pem_x509_certificate(cert.read_bytes())
    try:
        names = server.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return False
    return ipaddress.ip_address("127.0.0.1") in names.get_values_for_type(x509.IPAddress)


class FleetGateway:
    """ASGI app: ``POST /v1/fleet/<name>`` forwarded to ``upstream``, the rest refused (403)."""

    def __init__(self, upstream: str, verify: ssl.SSLContext | bool):
        self.internal = httpx.URL(upstream).netloc.decode()
        self.client = httpx.AsyncClient(
            base_url=upstream,
            verify=verify,
            timeout=httpx.Timeout(UPSTREAM_TIMEOUT_S, connect=10.0),
        )

    async def __call__(self, scope, receive, send) -> None:
        assert scope["type"] == "http", scope["type"]  # served with lifespan and websockets off
        response = await self._answer(Request(scope, receive))
        await response(scope, receive, send)

    async def _answer(self, request: Request) -> Response:
        path = request.scope["path"]  # percent-decoded by uvicorn: what the router would see
        if request.method != "POST" or not FLEET_PATH.fullmatch(path):
            peer = request.client.host if request.client else "?"
            _say(f"refused {request.method} {path[:120]!r} from {peer}")
            return PlainTextResponse(refusal(self.internal), status_code=403)
        # The query string is dropped: Flower's Fleet API reads the protobuf body only.
        outgoing = self.client.build_request(
            "POST", path, headers=_passed_on(request.headers.raw), content=request.stream()
        )
        try:
            answer = await self.client.send(outgoing, stream=True)
        except ClientDisconnect:
            return Response(status_code=400)  # nobody reads it
        except httpx.TransportError as err:  # refused, TLS, time-out
            _say(f"the SuperLink at {self.internal} did not answer {path}: {err!r}")
            return PlainTextResponse(
                f"fedlgr gateway: the SuperLink did not answer ({type(err).__name__})\n",
                status_code=502,
            )
        response = StreamingResponse(
            answer.aiter_raw(),
            status_code=answer.status_code,
            background=BackgroundTask(answer.aclose),
        )
        response.raw_headers = _passed_on(answer.headers.raw)  # keeps repeated headers
        return response


def _passed_on(headers: list[tuple[bytes, bytes]]) -> list[tuple[bytes, bytes]]:
    """``headers`` without the hop-by-hop ones (RFC 9110 7.6.1: those listed, and those
    that ``Connection`` names)."""
    named = {
        name.strip().lower()
        for key, value in headers
        if key.lower() == b"connection"
        for name in value.split(b",")
    }
    return [(k, v) for k, v in headers if k.lower() not in HOP_BY_HOP | named]


def run(
    superlink: list[str],
    env: dict[str, str],
    host: str,
    port: int,
    internal_port: int,
    tls: Tls | None,
    executor: list[str] | None = None,
) -> int:
    """Start the ``superlink`` command (Flower on 127.0.0.1:``internal_port``), then the
    ``executor`` SuperExec and the gateway on ``host``:``port`` (plain HTTP without ``tls``). Both
    children are stopped however this ends; either dying is a :class:`FedlgrError`."""
    listener = _bind(host, port)  # a port in use is refused before Flower starts
    children = [subprocess.Popen(superlink, env=env, preexec_fn=_die_with_parent)]
    try:
        _wait_listening(children[0], internal_port)
        if executor is not None:
            command = [*executor, "--parent-pid", str(children[0].pid)]
            children.append(subprocess.Popen(command, env=env, preexec_fn=_die_with_parent))
        asyncio.run(_serve(children, listener, internal_port, tls))
    finally:
        listener.close()
        with deferred():  # a signal now would cut the stop short
            for child in reversed(children):
                _stop(child)
    return 0


async def _serve(
    children: list[subprocess.Popen], listener: socket.socket, internal_port: int, tls: Tls | None
) -> None:
    scheme = "https" if tls else "http"
    verify = ssl.create_default_context(cafile=str(tls.ca)) if tls else False
    app = FleetGateway(f"{scheme}://127.0.0.1:{internal_port}", verify)
    config = uvicorn.Config(
        app,
        lifespan="off",
        ws="none",
        log_level="warning",
        access_log=False,  # Flower logs each request it is passed
        server_header=False,  # Flower's own Server and Date headers are passed on
        date_header=False,
        ssl_certfile=str(tls.cert) if tls else None,
        ssl_keyfile=str(tls.key) if tls else None,
    )
    server = uvicorn.Server(config)
    host, port = listener.getsockname()[:2]
    watch = asyncio.create_task(_watch(children, server))
    _say(f"serving {scheme}://{host}:{port} (Fleet API only) for the SuperLink at 127.0.0.1")
    try:
        # uvicorn re-raises SIGTERM/SIGINT once stopped: the caller's handler makes it an interrupt.
        await server.serve(sockets=[listener])
    finally:
        watch.cancel()
        await app.client.aclose()
    for child in children:
        if child.poll() is not None:
            raise FedlgrError(_ended(child))


async def _watch(children: list[subprocess.Popen], server: uvicorn.Server) -> None:
    while all(child.poll() is None for child in children):
        await asyncio.sleep(0.5)
    server.should_exit = True


def _bind(host: str, port: int) -> socket.socket:
    """A socket bound to ``host``:``port``, not listening yet (uvicorn listens on it)."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
        sock = socket.socket(family, kind, proto)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
    except OSError as err:
        raise FedlgrError(f"--host {host} --port {port}: cannot listen there ({err})") from None
    return sock


def _wait_listening(child: subprocess.Popen, port: int) -> None:
    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        if child.poll() is not None:
            raise FedlgrError(_ended(child))
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.2)
    raise FedlgrError(f"flower-superlink does not listen on 127.0.0.1:{port} after 300 s")


def _stop(child: subprocess.Popen) -> None:
    if child.poll() is None:
        child.terminate()
        try:
            child.wait(timeout=STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()


def _ended(child: subprocess.Popen) -> str:
    code = child.returncode
    how = f"exit {code}" if code >= 0 else f"killed by {signal.Signals(-code).name}"
    what = "its ServerApp executor" if EXECUTOR in child.args else "flower-superlink"
    return f"{what} ended ({how}); its log is above. The gateway stops too."


def _die_with_parent() -> None:
    """In the child before exec: on Linux, SIGTERM it when the gateway dies, even by SIGKILL
    (which runs no clean-up here)."""
    if sys.platform == "linux":
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG


def _say(text: str) -> None:
    print(f"fedlgr gateway: {text}", file=sys.stderr, flush=True)
