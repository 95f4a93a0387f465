"""The tracking store as a user meets it: where to look at the runs, the locks that let
several processes create a store (or a sweep's storage) at once, and opening it.

``open_client(uri)`` is the ``MlflowClient`` every command works with: the store is
reachable, created whole (a new sqlite file appears only once its schema is complete) and
migrated under :func:`store_lock`; ``store_errors`` turns a store's failure into one line.

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
import logging
import os
import shutil
import sqlite3
import sys
from pathlib import Path

from filelock import FileLock

from fedlgr.core.settings import default_cache_dir
from fedlgr.errors import FedlgrError, first_line
from fedlgr.shell.checks.stores import check_reachable, check_sqlite_usable, database_connection
from fedlgr.shell.tracking.uri import DATABASES, mask_password, masked_text, sqlite_file

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
    from sqlalchemy import text  # lazy: sqlalchemy (~1 s), only for a PostgreSQL store

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
    die on ``duplicate column name``). A ``filelock.FileLock`` beside the file: ``flock``
    underneath, so the kernel releases it when its holder dies, SIGKILL included. A
    PostgreSQL database (a store or a sweep's storage shared by several machines) takes an
    advisory lock of its own (:func:`database_lock`); other stores need no lock."""
    if not uri.startswith("sqlite:///"):
        with database_lock(uri):
            yield
        return
    path = Path(uri.removeprefix("sqlite:///").split("?", 1)[0]).expanduser()  # no ?mode=..
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = Path(f"{path}.lock")
    # Made here, a planted link refused: filelock opens it O_NOFOLLOW but does not promise to.
    os.close(open_lock_file(lock, f"tracking store {uri}"))
    with FileLock(lock, fallback_to_soft=False):  # no soft marker: it would outlive a kill
        yield


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


def open_client(uri: str):
    """An ``MlflowClient`` on ``uri`` whose store is created and migrated (under
    :func:`store_lock`)."""
    import mlflow  # lazy: mlflow (seconds), only once a command opens its store

    check_reachable(uri)
    # MLflow logs a failed store write (with its SQL and two stack traces) before raising
    # it; fedlgr's StoreError names the store and the cause in one line: only that is shown.
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.CRITICAL)
    with store_lock(uri):  # the client's construction creates and migrates the store
        if uri.startswith("sqlite:///"):
            check_sqlite_usable(uri)  # after the lock: a migration under way is not a fault
            create_whole(uri)
        client = mlflow.MlflowClient(uri)
        client.search_experiments(max_results=1)
    return client


def create_whole(uri: str) -> None:
    """Create a new sqlite store under a temporary name beside it and rename it into place
    once MLflow has made its whole schema: a kill during the creation (seconds) would leave
    a half-made store that no later run could use. Called under
    :func:`store_lock`, so a temporary file found is one a kill left behind."""
    import mlflow  # lazy: mlflow (seconds), only once a command opens its store

    path = sqlite_file(uri)
    if path is None or path.exists():
        return
    making = path.with_name(f".{path.name}.creating")
    making.unlink(missing_ok=True)
    empty = empty_store()
    if empty is not None:
        shutil.copyfile(empty, making)
    query = uri.partition("?")[2]
    mlflow.MlflowClient(f"sqlite:///{making}" + (f"?{query}" if query else "")).search_experiments(
        max_results=1
    )
    os.replace(making, path)


def empty_store() -> Path | None:
    """A migrated sqlite store with no experiment, made once per MLflow version and copied
    for every new store: MLflow's migrations take seconds, a copy milliseconds. MLflow puts
    its Default experiment's artifacts under the creating process's working folder, so the
    template has none: opening a copy creates it where a fresh store would.
    ``$FEDLGR_EMPTY_STORE`` names the file (default: in the cache folder); None where it
    cannot be made there (a new store is then migrated in place)."""
    import mlflow  # lazy: mlflow (seconds), only once a command opens its store

    default = default_cache_dir() / f"mlflow-{mlflow.__version__}-empty.db"
    path = Path(os.environ.get("FEDLGR_EMPTY_STORE", default))
    if path.is_file() and not path.is_symlink():
        return path
    making = path.with_name(f".{path.name}.{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        mlflow.MlflowClient(f"sqlite:///{making}").search_experiments(max_results=1)
        with contextlib.closing(sqlite3.connect(making)) as db, db:
            db.execute("DELETE FROM experiment_tags WHERE experiment_id = 0")
            db.execute("DELETE FROM experiments WHERE experiment_id = 0")
        os.replace(making, path)  # atomic: two processes making it at once both succeed
    except (OSError, sqlite3.Error):
        with contextlib.suppress(OSError):  # where the folder could not be made, nothing is
            making.unlink(missing_ok=True)
        return None
    return path


def _cause(err: BaseException) -> str:
    """The innermost reason, one line (an MLflow error wraps SQLAlchemy's wrapping
    sqlite's: "database or disk is full")."""
    while getattr(err, "orig", None) is not None or err.__cause__ is not None:
        err = getattr(err, "orig", None) or err.__cause__
    return first_line(err, 300)


@contextlib.contextmanager
def store_errors(uri: str, what: str):
    """An error of the store inside the block, as one line naming the store and what
    was being done (the CLI prints it without a stack trace)."""
    try:
        yield
    except FedlgrError:
        raise
    except Exception as err:
        problem = masked_text(_cause(err), uri)
        if problem == "database is locked":
            problem += (
                " (another process holds the sqlite file: one stopped with Ctrl-Z or "
                "kill -STOP? `kill -CONT PID` lets it go on)"
            )
        raise StoreError(f"MLflow store {mask_password(uri)}: could not {what}: {problem}") from err
