"""The tracking store as a user meets it: is it there, and where to look at the runs.

``check_reachable(uri)`` refuses an ``http(s)://`` tracking URI that nothing answers in a
few seconds, with one line that names it (MLflow's own client would retry for minutes,
then raise a long stack trace); a database server's URL (``postgresql://...``) is
connected to first (:func:`check_database`: driver, address, password, database), and
fedlgr's messages show its password masked (:func:`mask_password`).
``runs_hint(uri, experiment_id)`` is what ``fedlgr run``, ``demo`` and ``sweep`` print at
the end: the link that opens the experiment's runs table
and, for a local store, the ``mlflow ui`` command that serves it first.

MLflow 3 opens a browser that has not been there before on its GenAI pages (Traces,
"Detect Issues"); the runs table is the "Model training" workflow. Its single-page app
(``mlflow/server/js``) routes ``#/experiments/<id>/runs`` to that table and takes the
workflow from the ``workflowType`` query parameter before the browser's stored choice,
so the link below lands on the runs whatever the browser saw before.

Light on purpose (no MLflow import): the CLI calls it before loading torch.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import sys
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

from fedlgr.errors import FedlgrError, not_a_file

UI_PORT = 5000  # mlflow ui's default
# The runs table, in fedlgr's shared view of it (fedlgr.shell.tracking.views).
RUNS_VIEW = (
    "#/experiments/{experiment_id}/runs?workflowType=machine_learning&viewStateShareKey=fedlgr"
)
DATABASES = ("sqlite", "postgresql", "mysql", "mssql")


class TrackingUnreachable(FedlgrError):
    """Nothing answers at the tracking server's address."""


def in_memory_sqlite(uri: str) -> bool:
    """Whether ``uri`` names an in-memory sqlite database, which keeps nothing once its
    process ends: ``sqlite://``, ``:memory:``, or SQLite's URI filenames
    (``file::memory:``, ``mode=memory``)."""
    if not uri.startswith("sqlite:"):
        return False
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        url = make_url(uri)
    except (ArgumentError, ValueError):
        return False  # not a URL sqlalchemy reads: for the store's own check to refuse
    database = url.database or ""
    return (
        database in ("", ":memory:")
        or database.startswith("file::memory:")
        or url.query.get("mode") == "memory"
        or "mode=memory" in database
    )


def check_reachable(uri: str, timeout: float = 5.0) -> None:
    """Raise :class:`TrackingUnreachable` when ``uri`` is an HTTP(S) address at which
    nothing answers within ``timeout`` seconds. Any HTTP answer counts as reachable (a
    proxy's 401 or 404 is for MLflow to report). A local sqlite store must be one fedlgr
    can write (:func:`check_sqlite`); MLflow 3's plain file store is refused."""
    memory = in_memory_sqlite(uri)
    if uri.startswith("sqlite:///") and not memory:
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


def sqlite_path(uri: str) -> Path:
    return Path(uri.removeprefix("sqlite:///").split("?", 1)[0]).expanduser()


def check_sqlite(uri: str) -> None:
    """One line, before MLflow meets it, for a sqlite store that is a folder, not an
    SQLite file, read-only (or immutable), or in a folder that cannot be made or
    written. (MLflow would retry for minutes, or end in a stack trace.)"""
    path = sqlite_path(uri)
    if str(path) == ":memory:":
        return

    def refuse(why: str) -> None:
        raise TrackingUnreachable(f"tracking store {uri}: {why}")

    if path.is_dir():
        refuse(f"{path} is a folder; name the database file in it, e.g. sqlite:///{path}/mlflow.db")
    if why := not_a_file(path):  # a new store would replace a link (u79, u50); a FIFO
        refuse(f"{path} is {why}")  # hung, /dev/null made /dev/null-journal (c06, c07)
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
    """The sqlite store opens and takes a write lock within ``wait`` seconds: a corrupted
    file, or one that another process keeps locked, is one line (MLflow would retry for
    minutes, then end in a stack trace)."""
    import sqlite3

    path = sqlite_path(uri)
    if not path.is_file() or str(path) == ":memory:":
        return
    try:
        connection = sqlite3.connect(path, timeout=wait)
        try:
            connection.execute("SELECT count(*) FROM sqlite_master").fetchone()
            half_created(connection)
            if path.stat().st_size < QUICK_CHECK_BYTES:  # ~20 ms per MB: skipped for big ones
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
    """Raise ``sqlite3.DatabaseError`` for an MLflow store whose creation a kill cut short
    (the seventh fault sweep, g03e: its tables there, ``alembic_version`` empty, and every
    later use a ``duplicate column name`` traceback). fedlgr now creates a store under
    another name and renames it when whole (:func:`fedlgr.shell.tracking.mlflow_run.open_client`);
    this names the ones left by other tools or earlier versions."""
    import sqlite3

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


def check_tracking(uri: str | None, overrides: list[str]) -> None:
    """:func:`check_reachable` on the URI a command was given: ``--tracking-uri``, else
    its last ``tracking.uri=`` override, else ``$MLFLOW_TRACKING_URI``."""
    check_reachable(given_uri(uri, overrides))


def given_uri(uri: str | None, overrides: list[str]) -> str:
    """The tracking URI a command was given: ``--tracking-uri``, else its last
    ``tracking.uri=`` override, else ``$MLFLOW_TRACKING_URI`` or the default."""
    from fedlgr.shell.tracking.mlflow_run import resolve_uri

    given = [o.split("=", 1)[1] for o in overrides if o.startswith("tracking.uri=")]
    return resolve_uri(uri or (given[-1] if given else None))


def runs_link(server: str, experiment_id: str) -> str:
    """The UI address that opens experiment ``experiment_id``'s runs table."""
    return f"{server.rstrip('/')}/{RUNS_VIEW.format(experiment_id=experiment_id)}"


def runs_hint(uri: str, experiment_id: str) -> str:
    """What to open to see the runs: the link for a server; for a database store, the
    ``mlflow ui`` command that serves it, then the link. Empty for other stores."""
    scheme = uri.split(":", 1)[0].split("+", 1)[0]
    if scheme in ("http", "https"):
        return f"MLflow runs: {runs_link(uri, experiment_id)}"
    if scheme not in DATABASES:
        return ""
    store = _absolute_sqlite(uri) if scheme == "sqlite" else mask_password(uri)
    link = runs_link(f"http://127.0.0.1:{UI_PORT}", experiment_id)
    return (
        f"MLflow runs: start the UI with\n  {_mlflow()} ui --backend-store-uri {store} "
        f"--port {UI_PORT}\nthen open {link}"
    )


def _absolute_sqlite(uri: str) -> str:
    """``sqlite:///mlflow.db`` -> ``sqlite:////work/mlflow.db``: the command works from
    any folder."""
    path = uri.removeprefix("sqlite:///")
    if uri.startswith("sqlite:///") and path and path != ":memory:":
        return "sqlite:///" + str(Path(path).expanduser().resolve())
    return uri


def _mlflow() -> str:
    """How to call MLflow's command here: through uv when fedlgr runs under ``uv run``,
    else the ``mlflow`` on PATH, else this interpreter's module."""
    if os.environ.get("UV"):
        return "uv run mlflow"
    if shutil.which("mlflow"):
        return "mlflow"
    return f"{sys.executable} -m mlflow"


# --------------------------------------------------------------------------- database servers


def mask_password(uri: str) -> str:
    """``uri`` with the password of its ``user:password@`` part as ``***`` (also one that
    holds ``/`` or ``@``, or in a URL no parser reads), and the value of every query
    parameter named ``...password`` (libpq reads ``password`` and ``sslpassword`` there,
    also percent-encoded, ``pass%77ord``): what fedlgr prints of a URI."""
    scheme, sep, rest = uri.partition("://")
    if not sep:
        return uri
    end = _authority_end(rest)
    at = rest.rfind("@", 0, end)
    user, colon, _ = rest[: max(at, 0)].partition(":")
    if at >= 0 and colon and "/" not in user:
        rest = f"{user}:***{rest[at:]}"
    return f"{scheme}://" + _QUERY_PARAM.sub(_masked_param, rest)


# a query (or fragment) parameter: its separator, name and value
_QUERY_PARAM = re.compile(r"([?&#;])([^=&#;]*)=([^&#;]*)")


def _secret_param(name: str) -> bool:
    return urllib.parse.unquote(name).strip().lower().endswith("password")


def _masked_param(m: re.Match) -> str:
    return f"{m.group(1)}{m.group(2)}=***" if _secret_param(m.group(2)) else m.group(0)


def _authority_end(rest: str) -> int:
    """Where the query or fragment of a URL (after its ``scheme://``) begins."""
    return min((i for i in (rest.find("?"), rest.find("#")) if i >= 0), default=len(rest))


def _secrets(uri: str) -> set[str]:
    """The passwords ``uri`` holds (in its ``user:password@`` part and its query), as
    written and decoded, and each part of one that holds ``@`` (a parser that splits the
    URL at its first ``@`` shows the rest as a host name)."""
    _, sep, rest = uri.partition("://")
    if not sep:
        return set()
    end = _authority_end(rest)
    at = rest.rfind("@", 0, end)
    found = {rest[:at].partition(":")[2]} if at > 0 else set()
    found |= {m.group(3) for m in _QUERY_PARAM.finditer(rest) if _secret_param(m.group(2))}
    forms = found | {urllib.parse.unquote(f) for f in found}
    forms |= {part for f in forms for part in f.split("@")}
    return {f for f in forms if len(f) >= 3}


def check_userinfo(uri: str, what: str, error: type[FedlgrError] = FedlgrError) -> None:
    """A ``user:password@`` part that holds an unescaped ``@``: URL parsers disagree on
    where it ends (libpq splits at the first ``@``, SQLAlchemy at the last), so one of them
    would take the tail of the password for a host name - and print it. One line asking for
    ``%40``."""
    _, sep, rest = uri.partition("://")
    authority = rest[: _authority_end(rest)].split("/", 1)[0]
    if sep and authority.count("@") > 1:
        raise error(
            f"{what} {mask_password(uri)}: its user or password holds an '@': write it "
            "percent-encoded, %40 (and ':' as %3A, '/' as %2F)"
        )


def server_database(uri: str) -> bool:
    """Whether ``uri`` names a database server's database (``postgresql://``,
    ``postgresql+psycopg://``, ``mysql+pymysql://``, ...) rather than a file or an
    HTTP server; also a misspelt one (``postgres://``), for :func:`check_database` to name."""
    scheme = uri.partition("://")[0].split("+", 1)[0].lower() if "://" in uri else ""
    return scheme in (*DATABASES[1:], "postgres", "mariadb")


DRIVER_HINTS = {
    "psycopg": "the PostgreSQL driver psycopg is not installed: `uv sync --extra postgres` "
    "(pip: fedlgr[postgres])",
    "psycopg2": "its driver psycopg2 is not installed: install it, or use postgresql:// "
    "(psycopg 3: `uv sync --extra postgres`)",
}


CONNECT_TIMEOUT_S = 10  # for a database server to answer


def check_database(uri: str, what: str, error: type[FedlgrError] = FedlgrError) -> None:
    """Connect to the server database ``uri`` (:data:`CONNECT_TIMEOUT_S`) and leave: a URL
    SQLAlchemy cannot read, an unknown kind or driver, a driver that is not installed, a
    server that does not answer, a wrong user or password, a missing database are one
    ``error`` line ``{what} {uri}: {problem}``, the password masked (MLflow would retry
    for minutes; Optuna and SQLAlchemy end in stack traces)."""
    with _database_connection(uri, what, error):
        pass


@contextlib.contextmanager
def _database_connection(uri: str, what: str, error: type[FedlgrError]):
    """An open SQLAlchemy connection to ``uri`` (no pool: closed for good at the end);
    failing to open it is one ``error`` line (:func:`database_problem`)."""
    from sqlalchemy import create_engine
    from sqlalchemy.pool import NullPool

    def fail(problem: str) -> FedlgrError:
        return error(f"{what} {mask_password(uri)}: {masked_text(problem, uri)}")

    check_userinfo(uri, what, error)
    engine = None
    try:
        from sqlalchemy.engine import make_url

        url = make_url(uri)
        backend = url.get_backend_name()
        # The URI's own connect_timeout, if it names one, is tried as written (a bad value
        # is one line now, not two minutes of MLflow's retries later)
        timed = backend in ("postgresql", "mysql") and "connect_timeout" not in url.query
        args = {"connect_timeout": CONNECT_TIMEOUT_S} if timed else {}
        engine = create_engine(url, poolclass=NullPool, connect_args=args)
        connection = engine.connect()
    except Exception as err:
        if engine is not None:
            engine.dispose()
        raise fail(database_problem(uri, err)) from None
    try:
        yield connection
    finally:
        with contextlib.suppress(Exception):
            connection.close()
        engine.dispose()


def database_problem(uri: str, err: BaseException) -> str:
    """What an error of opening a connection to ``uri`` means, in a few words."""
    from sqlalchemy.exc import ArgumentError, NoSuchModuleError

    scheme = uri.partition("://")[0]
    if isinstance(err, NoSuchModuleError):
        if scheme.split("+", 1)[0] == "postgres":
            return f"unknown database kind {scheme!r}: PostgreSQL's URLs begin postgresql://"
        return (
            f"unknown database kind or driver {scheme!r} (e.g. postgresql://, "
            "postgresql+psycopg://, mysql+pymysql://)"
        )
    if isinstance(err, ArgumentError | ValueError):
        return f"not a database URL ({_first_line(err)}); e.g. postgresql://USER@HOST:5432/DATABASE"
    if isinstance(err, ImportError):
        name = (getattr(err, "name", None) or "").split(".")[0]
        return DRIVER_HINTS.get(name) or f"its driver {name or err} is not installed"
    text = _first_line(getattr(err, "orig", None) or err)
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
    from sqlalchemy.engine import make_url

    try:
        url = make_url(uri)
        return f"{url.host or 'localhost'}:{url.port or 'default port'}"
    except Exception:
        return "its address"


def _first_line(err: BaseException) -> str:
    return (str(err).strip().splitlines() or [type(err).__name__])[0].strip()


def masked_text(text: str, uri: str) -> str:
    """``text`` without the URI's passwords: the URI as :func:`mask_password` writes it, and
    each password elsewhere (three characters or more), as written or decoded, and each
    ``@``-separated part of one."""
    text = text.replace(uri, mask_password(uri))
    for form in sorted(_secrets(uri), key=len, reverse=True):
        text = text.replace(form, "***")
    return text


# An advisory lock's key (any 64-bit number): held while a process opens a study or an
# MLflow store on a PostgreSQL database, as the lock file is beside an sqlite file.
LOCK_KEY = 0x666564_6C6772  # "fedlgr"


@contextlib.contextmanager
def database_lock(uri: str, what: str = "database"):
    """Held while a process creates tables, a study or a parent run in the PostgreSQL
    database ``uri``: an advisory lock of the database (``pg_advisory_lock``), which the
    server releases when the holder's connection ends - a killed process included. Two
    processes that create Optuna's or MLflow's tables in a fresh database at once would
    make one fail (a duplicate key in ``pg_type``). Other databases are not locked."""
    if not uri.lower().startswith(("postgresql:", "postgresql+")):
        yield
        return
    from sqlalchemy import text

    with _database_connection(uri, what, FedlgrError) as connection:
        connection.execute(text("SELECT pg_advisory_lock(:key)"), {"key": LOCK_KEY})
        connection.commit()  # a session lock: no transaction left open while it is held
        try:
            yield
        finally:
            with contextlib.suppress(Exception):
                connection.execute(text("SELECT pg_advisory_unlock(:key)"), {"key": LOCK_KEY})


def masked_echo(echo, *uris: str | None):
    """``echo`` (e.g. ``print``) that writes the passwords of ``uris`` as ``***``: what a
    command prints of its URIs (the study's storage, the tracking store)."""
    given = [u for u in uris if u]

    def say(*args: object, **kwargs) -> None:
        text = " ".join(map(str, args))
        for uri in given:
            text = masked_text(text, uri)
        echo(text, **kwargs)

    return say
