"""A real PostgreSQL server for the tests, made and started by the test itself: Debian's
``postgresql`` package's ``initdb`` in a temporary folder, ``pg_ctl`` on a free localhost
port (TCP only, password authentication), stopped and removed at the end.

PostgreSQL refuses to run as root: under root (CI, these machines) the server's folder
belongs to ``nobody`` and ``initdb``, ``pg_ctl`` and the server run as that user.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import secrets
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

from tests.support.ports import free_port

USER = "fedlgr"
SERVER_USER = "nobody"  # who runs the server when the tests run as root


def find_binary(name: str) -> str | None:
    """``name`` on PATH, else in Debian's ``/usr/lib/postgresql/VERSION/bin`` (the package
    puts only psql and the like on PATH), the newest version first."""
    found = shutil.which(name)
    if found:
        return found
    versions = sorted(
        Path("/usr/lib/postgresql").glob(f"*/bin/{name}"),
        key=lambda p: int(p.parts[-3]) if p.parts[-3].isdigit() else 0,
        reverse=True,
    )
    return str(versions[0]) if versions else None


def missing() -> str | None:
    """Why a server cannot be made here (None when it can)."""
    for name in ("initdb", "pg_ctl"):
        if find_binary(name) is None:
            return (
                f"PostgreSQL's {name} is not installed (Debian: apt-get install postgresql; "
                ".ci/run installs it where it can)"
            )
    return None


class PostgresServer:
    """One server; :meth:`uri` gives a SQLAlchemy URL of one of its databases."""

    def __init__(self) -> None:
        self.password = secrets.token_hex(8)
        self.port = free_port()
        # Under root, a folder that ``nobody`` can reach: pytest's temp folders are 0700.
        where = "/tmp" if os.geteuid() == 0 else None
        self.root = Path(tempfile.mkdtemp(prefix="fedlgr-pg-", dir=where))
        self.data = self.root / "data"
        self.log = self.root / "server.log"
        self.as_user: dict = {}
        if os.geteuid() == 0:
            who = pwd.getpwnam(SERVER_USER)
            os.chown(self.root, who.pw_uid, who.pw_gid)
            self.as_user = {"user": who.pw_uid, "group": who.pw_gid, "extra_groups": []}

    def _run(self, *command: str) -> None:
        done = subprocess.run(
            command,
            capture_output=True,
            text=True,
            env={**os.environ, "LC_ALL": "C", "TZ": "UTC"},
            timeout=120,
            cwd=self.root,
            **self.as_user,
        )
        if done.returncode != 0:
            log = self.log.read_text()[-2000:] if self.log.is_file() else ""
            raise RuntimeError(
                f"{' '.join(command)} failed ({done.returncode}): {done.stderr[-2000:]} {log}"
            )

    def start(self) -> PostgresServer:
        password_file = self.root / "password"
        password_file.write_text(self.password + "\n")
        if self.as_user:
            os.chown(password_file, self.as_user["user"], self.as_user["group"])
        self._run(
            find_binary("initdb"),
            "-D",
            str(self.data),
            "-U",
            USER,
            f"--pwfile={password_file}",
            "--auth-host=scram-sha-256",
            "--auth-local=scram-sha-256",
            "--encoding=UTF8",
            "--locale=C",
            "--no-sync",  # a throwaway server: no fsync of its files
        )
        password_file.unlink()
        options = (
            f"-c listen_addresses=127.0.0.1 -p {self.port} -c unix_socket_directories='' "
            "-c fsync=off -c synchronous_commit=off -c full_page_writes=off"
        )
        self._run(
            find_binary("pg_ctl"), "start", "-w", "-t", "60", "-D", str(self.data),
            "-l", str(self.log), "-o", options,
        )  # fmt: skip
        return self

    def stop(self) -> None:
        if (self.data / "postmaster.pid").exists():
            with contextlib.suppress(RuntimeError, subprocess.TimeoutExpired):
                self._run(find_binary("pg_ctl"), "stop", "-w", "-m", "fast", "-D", str(self.data))
        shutil.rmtree(self.root, ignore_errors=True)

    def uri(self, database: str, password: str | None = None, scheme: str = "postgresql") -> str:
        secret = self.password if password is None else password
        return f"{scheme}://{USER}:{secret}@127.0.0.1:{self.port}/{database}"

    def connect(self, database: str):
        """A psycopg connection to ``database`` (autocommit)."""
        import psycopg

        return psycopg.connect(self.uri(database), autocommit=True)

    def create_database(self, name: str) -> str:
        """A new, empty database; its URI."""
        with self.connect("postgres") as connection:
            connection.execute(f'CREATE DATABASE "{name}"')
        return self.uri(name)


@contextlib.contextmanager
def postgres_server() -> Iterator[PostgresServer]:
    server = PostgresServer()
    try:
        yield server.start()
    finally:
        server.stop()
