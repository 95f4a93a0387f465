"""Is a tracking store or a sweep's storage there and usable: one line before anything is written
(MLflow would retry for minutes). Light on purpose (no MLflow import): read before torch loads."""

from __future__ import annotations

import contextlib
import os
import re
import sqlite3

from fedlgr.errors import FedlgrError, first_line
from fedlgr.shell.checks.paths import not_a_file
from fedlgr.shell.tracking.uri import (
    authority_end,
    in_memory_sqlite,
    mask_password,
    masked_text,
    server_database,
    sqlite_file,
)


class TrackingUnreachable(FedlgrError):
    """Nothing answers at the tracking server's address."""


def check_reachable(uri: str, timeout: float = 5.0) -> None:
    """Raise :class:`TrackingUnreachable` when ``uri`` is an HTTP(S) address at which nothing
    answers within ``timeout`` seconds (any HTTP answer counts). A sqlite store must be one fedlgr
    can write; a plain file store is refused."""
    if uri.startswith("sqlite:///") and not in_memory_sqlite(uri):
        check_sqlite(uri)
        return
    if uri.startswith("sqlite:"):  # sqlite:// or sqlite:///:memory: - no file
        raise TrackingUnreachable(
            f"tracking URI {uri}: an in-memory sqlite store keeps nothing (the run is lost "
            "when this process ends); name a file: sqlite:///PATH/mlflow.db (the default: "
            "sqlite:///mlflow.db)"
        )
    if uri.startswith("file:") or "://" not in uri:
        raise TrackingUnreachable(
            f"tracking URI {uri}: a plain file store, which MLflow 3 keeps in maintenance "
            "mode and fedlgr does not use; give sqlite:///PATH/mlflow.db (the default: "
            "sqlite:///mlflow.db) or an mlflow server's http://HOST:PORT"
        )
    if server_database(uri):
        check_database(uri, "tracking URI", TrackingUnreachable)
        return
    if not uri.startswith(("http://", "https://")):
        return
    # lazy: urllib.request, for a server's URI only
    import urllib.error
    import urllib.request

    probe = uri.rstrip("/") + "/health"
    try:
        with urllib.request.urlopen(probe, timeout=timeout):
            pass
    except urllib.error.HTTPError:
        return  # something answered
    except (OSError, ValueError) as err:
        reason = masked_text(str(getattr(err, "reason", err)), uri)
        raise TrackingUnreachable(
            f"tracking URI {mask_password(uri)}: no MLflow server answers there ({reason}); "
            "start one (`mlflow server --host 127.0.0.1 --port PORT`), fix --tracking-uri / "
            "$MLFLOW_TRACKING_URI, or leave both unset for the local sqlite store"
        ) from None


SQLITE_HEADER = b"SQLite format 3\x00"


def check_sqlite(uri: str) -> None:
    """One line, before MLflow meets it, for a sqlite store that is a folder, not an SQLite file,
    read-only, or in a folder that cannot be made or written."""
    from sqlalchemy.exc import ArgumentError  # lazy: SQLAlchemy, a sqlite store only

    def refuse(why: str) -> None:
        raise TrackingUnreachable(f"tracking store {uri}: {why}")

    try:
        path = sqlite_file(uri)
    except ArgumentError:
        refuse("not a database URL (e.g. sqlite:///mlflow.db)")
    if path is None:
        return

    if path.is_dir():
        refuse(f"{path} is a folder; name the database file in it, e.g. sqlite:///{path}/mlflow.db")
    # sqlite would replace a link, hang on a FIFO and write /dev/null-journal beside /dev/null
    if why := not_a_file(path):
        refuse(f"{path} is {why}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        refuse(f"cannot create its folder {path.parent} ({err.strerror or err})")
    if not os.access(path.parent, os.W_OK):
        refuse(f"its folder {path.parent} is not writable (sqlite writes a journal next to it)")
    if path.exists():
        try:
            with path.open("rb") as handle:
                head = handle.read(len(SQLITE_HEADER))
        except OSError as err:
            refuse(f"cannot read {path} ({err.strerror or err})")
        if head and head != SQLITE_HEADER:
            refuse(f"{path} is not an SQLite database (another file is there)")
        if not os.access(path, os.W_OK):
            refuse(f"{path} is read-only (or immutable: lsattr); runs could not be recorded")


QUICK_CHECK_BYTES = 256 * 2**20


def check_sqlite_usable(uri: str, wait: float = 30.0) -> None:
    """The sqlite store opens and takes a write lock within ``wait`` seconds: a corrupted file, or
    one another process keeps locked, is one line."""
    path = sqlite_file(uri)
    if path is None or not path.is_file():
        return
    try:
        connection = sqlite3.connect(path, timeout=wait)
        try:
            connection.execute("SELECT count(*) FROM sqlite_master").fetchone()
            half_created(connection)
            if path.stat().st_size < QUICK_CHECK_BYTES:  # it reads the whole file
                problems = connection.execute("PRAGMA quick_check(1)").fetchone()
                if problems and problems[0] != "ok":
                    found = " ".join(problems[0].split())
                    raise sqlite3.DatabaseError(f"database disk image is malformed: {found}")
            connection.execute("BEGIN IMMEDIATE")
            connection.rollback()
        finally:
            connection.close()
    except sqlite3.DatabaseError as err:
        if "locked" in str(err):
            why = f"another process has kept it locked for over {wait:.0f} s"
        elif str(err).startswith("half-created"):
            why = f"{path} is {err}"
        else:
            why = f"{path} is damaged ({err}); restore it from a copy, or start a new store"
        raise TrackingUnreachable(f"tracking store {uri}: {why}") from None


def half_created(connection) -> None:
    """Raise ``sqlite3.DatabaseError`` for an MLflow store whose creation a kill cut short (tables
    there, ``alembic_version`` empty): its every use would be a ``duplicate column name``
    traceback."""
    tables = {name for (name,) in connection.execute("SELECT name FROM sqlite_master")}
    if not tables or "experiments" not in tables:
        return  # an empty file, or not MLflow's (refused as such elsewhere)
    version = (
        "alembic_version" in tables
        and connection.execute("SELECT count(*) FROM alembic_version").fetchone()[0]
    )
    if not version:
        runs = "runs" in tables and connection.execute("SELECT count(*) FROM runs").fetchone()[0]
        hint = "it holds no runs: remove it" if not runs else f"it holds {runs} runs"
        raise sqlite3.DatabaseError(
            f"half-created (its schema has no version: a process was killed while MLflow "
            f"created it; {hint})"
        )


def check_userinfo(uri: str, what: str, error: type[FedlgrError] = FedlgrError) -> None:
    """Refuse a ``user:password@`` part holding an unescaped ``@``: libpq splits at the first ``@``,
    SQLAlchemy at the last, so one would print the password's tail as a host name."""
    _, sep, rest = uri.partition("://")
    authority = rest[: authority_end(rest)].split("/", 1)[0]
    if sep and authority.count("@") > 1:
        raise error(
            f"{what} {mask_password(uri)}: its user or password holds an '@': write it "
            "percent-encoded, %40 (and ':' as %3A, '/' as %2F)"
        )


DRIVER_HINTS = {
    "psycopg": "the PostgreSQL driver psycopg is not installed: `uv sync --extra postgres` "
    "(pip: fedlgr[postgres])",
    "psycopg2": "its driver psycopg2 is not installed: install it, or use postgresql:// "
    "(psycopg 3: `uv sync --extra postgres`)",
}


CONNECT_TIMEOUT_S = 10  # for a database server to answer


def check_database(uri: str, what: str, error: type[FedlgrError] = FedlgrError) -> None:
    """Connect to the server database ``uri`` and leave: an unreadable URL, a missing driver, no
    answer, a wrong password or a missing database is one ``error`` line, password masked."""
    with database_connection(uri, what, error):
        pass


@contextlib.contextmanager
def database_connection(uri: str, what: str, error: type[FedlgrError]):
    """An open SQLAlchemy connection to ``uri`` (no pool: closed for good at the end);
    failing to open it is one ``error`` line (:func:`database_problem`)."""
    # lazy: SQLAlchemy, only for a database server's URL
    from sqlalchemy import create_engine, make_url
    from sqlalchemy.pool import NullPool

    check_userinfo(uri, what, error)
    engine = None
    try:
        url = make_url(uri)
        backend = url.get_backend_name()
        # The URI's own connect_timeout, if any, is tried as written: a bad value fails now
        timed = backend in ("postgresql", "mysql") and "connect_timeout" not in url.query
        args = {"connect_timeout": CONNECT_TIMEOUT_S} if timed else {}
        engine = create_engine(url, poolclass=NullPool, connect_args=args)
        connection = engine.connect()
    except Exception as err:
        if engine is not None:
            engine.dispose()
        problem = masked_text(database_problem(uri, err), uri)
        raise error(f"{what} {mask_password(uri)}: {problem}") from None
    try:
        yield connection
    finally:
        with contextlib.suppress(Exception):
            connection.close()
        engine.dispose()


def database_problem(uri: str, err: BaseException) -> str:
    """What an error of opening a connection to ``uri`` means, in a few words."""
    from sqlalchemy.exc import ArgumentError, NoSuchModuleError  # lazy: SQLAlchemy

    scheme = uri.partition("://")[0]
    if isinstance(err, NoSuchModuleError):
        if scheme.split("+", 1)[0] == "postgres":
            return f"unknown database kind {scheme!r}: PostgreSQL's URLs begin postgresql://"
        return (
            f"unknown database kind or driver {scheme!r} (e.g. postgresql://, "
            "postgresql+psycopg://, mysql+pymysql://)"
        )
    if isinstance(err, ArgumentError | ValueError):
        return f"not a database URL ({first_line(err)}); e.g. postgresql://USER@HOST:5432/DATABASE"
    if isinstance(err, ImportError):
        name = (getattr(err, "name", None) or "").split(".")[0]
        return DRIVER_HINTS.get(name) or f"its driver {name or err} is not installed"
    text = first_line(getattr(err, "orig", None) or err)
    for prefix in ("connection failed: ", "connection is bad: "):
        text = text.removeprefix(prefix)
    # psycopg: 'connection to server at "HOST", port PORT failed: FATAL:  WHY'
    text = re.sub(r"^connection to server (at|on) .*? failed: ", "", text)
    text = re.sub(r"^(FATAL|ERROR):\s+", "", text).strip()
    address = _address(uri)
    if "Connection refused" in text or "No such file or directory" in text:
        return (
            f"no database server answers at {address} ({text.lower()}): is it running, "
            "and are the host and port right?"
        )
    if "timeout expired" in text or "timed out" in text.lower():
        return f"no answer from {address} within {CONNECT_TIMEOUT_S} s ({text})"
    if "password authentication failed" in text or "no password supplied" in text:
        return (
            f"{text}: a wrong user or password (it can come from ~/.pgpass or "
            "$PGPASSWORD instead of the URL)"
        )
    if "does not exist" in text and "database" in text:
        return f"{text} on {address} (create it first: createdb, or CREATE DATABASE)"
    return f"cannot connect: {text}"


def _address(uri: str) -> str:
    from sqlalchemy.engine import make_url  # lazy: SQLAlchemy, a server's URL only

    try:
        url = make_url(uri)
        return f"{url.host or 'localhost'}:{url.port or 'default port'}"
    except Exception:
        return "its address"
