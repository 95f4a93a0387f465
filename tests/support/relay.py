"""What a robot really receives from its SuperLink: a TLS relay on localhost between one
SuperNode and the SuperLink's port. It serves with the federation's server certificate (which
the robot trusts through ``ca.pem``), connects on over TLS checked against ``ca.pem``, passes
every byte on both ways unchanged, and keeps the responses' bodies the robot was sent,
decrypted and unframed (HTTP/1.1: SuperNodes send unary requests)."""

from __future__ import annotations

import asyncio
import contextlib
import ssl
import threading
from pathlib import Path

from .ports import free_port


class TlsRelay:
    """Listens on ``self.port`` (give it to the SuperNode as its SuperLink) and forwards to
    127.0.0.1:``upstream``; :meth:`bodies` is what came back."""

    def __init__(self, upstream: int, creds: Path):
        self.upstream = upstream
        self.port = free_port()
        self.streams: list[bytearray] = []  # per connection, the bytes sent to the robot
        self.serving = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        self.serving.load_cert_chain(creds / "server.pem", creds / "server.key")
        self.checking = ssl.create_default_context(cafile=str(creds / "ca.pem"))
        self.loop = asyncio.new_event_loop()
        ready = threading.Event()
        self.thread = threading.Thread(target=self._run, args=(ready,), daemon=True)
        self.thread.start()
        assert ready.wait(30), "the relay did not start"

    def _run(self, ready: threading.Event) -> None:
        asyncio.set_event_loop(self.loop)
        server = self.loop.run_until_complete(
            asyncio.start_server(self._relay, "127.0.0.1", self.port, ssl=self.serving)
        )
        ready.set()
        self.loop.run_forever()
        server.close()

    async def _relay(self, robot_in, robot_out) -> None:
        try:
            link_in, link_out = await asyncio.open_connection(
                "127.0.0.1", self.upstream, ssl=self.checking, server_hostname="127.0.0.1"
            )
        except OSError:
            robot_out.close()
            return
        received = bytearray()
        self.streams.append(received)
        await asyncio.gather(_pump(robot_in, link_out, None), _pump(link_in, robot_out, received))

    def bodies(self) -> bytes:
        """Every response body the robot was sent, one after another."""
        return b"".join(body for stream in list(self.streams) for body in _bodies(bytes(stream)))

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=30)


async def _pump(source, sink, kept: bytearray | None) -> None:
    with contextlib.suppress(OSError, ssl.SSLError, asyncio.IncompleteReadError):
        while data := await source.read(65536):
            if kept is not None:
                kept += data
            sink.write(data)
            await sink.drain()
    with contextlib.suppress(OSError, ssl.SSLError):
        sink.close()


def _bodies(stream: bytes) -> list[bytes]:
    """The bodies of the HTTP/1.1 responses in ``stream`` (Content-Length or chunked; a
    compressed body would hide its text, so none is accepted)."""
    out = []
    while stream:
        head, _, stream = stream.partition(b"\r\n\r\n")
        headers = dict(
            (k.strip().lower(), v.strip())
            for k, _, v in (line.partition(b":") for line in head.split(b"\r\n")[1:])
        )
        assert headers.get(b"content-encoding", b"identity") == b"identity", headers
        if headers.get(b"transfer-encoding", b"").lower() == b"chunked":
            body = bytearray()
            while True:
                size, _, stream = stream.partition(b"\r\n")
                n = int(size.split(b";")[0], 16)
                body += stream[:n]
                stream = stream[n + 2 :]
                if n == 0:
                    break
            out.append(bytes(body))
        else:
            n = int(headers.get(b"content-length", b"0"))
            out.append(stream[:n])
            stream = stream[n:]
    return out
