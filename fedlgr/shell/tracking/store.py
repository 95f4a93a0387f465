"""The tracking store as a user meets it: where to look at the runs, and the locks that
let several processes create a store (or a sweep's storage) at once.

``runs_hint(uri, experiment_id)`` is what ``fedlgr run``, ``demo`` and ``sweep`` print at
the end: the link that opens the experiment's runs table and, for a local store, the
``mlflow ui`` command that serves it first.

MLflow 3 opens a browser that has not been there before on its GenAI pages (Traces,
"Detect Issues"); the runs table is the "Model training" workflow. Its single-page app
(``mlflow/server/js``) routes ``#/experiments/<id>/runs`` to that table and takes the
workflow from the ``workflowType`` query parameter before the browser's stored choice,
so the link below lands on the runs whatever the browser saw before.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import sys
from pathlib import Path

from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.stores import database_connection
from fedlgr.shell.tracking.uri import DATABASES, mask_password

UI_PORT = 5000  # mlflow ui's default


# The runs table, in fedlgr's shared view of it (fedlgr.shell.tracking.views).
RUNS_VIEW = (
    "#/experiments/{experiment_id}/runs?workflowType=machine_learning&viewStateShareKey=fedlgr"
)


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

    with database_connection(uri, what, FedlgrError) as connection:
        connection.execute(text("SELECT pg_advisory_lock(:key)"), {"key": LOCK_KEY})
        connection.commit()  # a session lock: no transaction left open while it is held
        try:
            yield
        finally:
            with contextlib.suppress(Exception):
                connection.execute(text("SELECT pg_advisory_unlock(:key)"), {"key": LOCK_KEY})


class StoreError(FedlgrError):
    """The tracking store refused a write (full disk, lost server, locked file)."""


@contextlib.contextmanager
def store_lock(uri: str):
    """Held while a process opens a local sqlite store: the first use of a fresh store
    runs MLflow's schema migrations, which two processes must not run at once (one would
    die on ``duplicate column name``). A PostgreSQL database (a store or a sweep's
    storage shared by several machines) takes an advisory lock of its own
    (:func:`database_lock`); other stores need no lock."""
    if not uri.startswith("sqlite:///"):
        with database_lock(uri):
            yield
        return
    path = Path(uri.removeprefix("sqlite:///").split("?", 1)[0]).expanduser()  # no ?mode=..
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = open_lock_file(Path(f"{path}.lock"), f"tracking store {uri}")
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def open_lock_file(path: Path, what: str) -> int:
    """The descriptor of the lock file ``path`` beside a store, created if missing (empty,
    0644). O_NOFOLLOW: a link planted there is refused, not a way to create or truncate a
    file elsewhere (``flock`` needs no content, so nothing is written)."""
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise StoreError(f"{what}: its lock file {path} is a symbolic link: refused") from None
        raise StoreError(f"{what}: cannot open its lock file {path}: {err.strerror}") from None
