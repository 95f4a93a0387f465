"""The tracking store as a user meets it: opening it (created whole and migrated under a lock, as
several processes may open it at once), its errors as one line, and where to look at the runs."""

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


# The runs table ("Model training", not MLflow 3's GenAI pages), in fedlgr's shared view of it.
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
    """``sqlite:///mlflow.db`` -> ``sqlite:////work/mlflow.db``, so the command works anywhere."""
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


# the key (any 64-bit number) of the PostgreSQL advisory lock that stands for the lock file
LOCK_KEY = 0x666564_6C6772  # "fedlgr"


@contextlib.contextmanager
def database_lock(uri: str, what: str = "database"):
    """Held while a process creates tables, a study or a parent run in the PostgreSQL database
    ``uri``: two processes creating Optuna's or MLflow's tables at once make one fail (a duplicate
    key in ``pg_type``). The server releases it when the holder's connection ends."""
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
    """Held while a process opens a store: two processes running MLflow's schema migrations at once
    make one die (``duplicate column name``). ``flock`` beside an sqlite file, which the kernel
    releases when its holder dies; :func:`database_lock` for PostgreSQL."""
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
    """The descriptor of the lock file ``path`` beside a store, created if missing. O_NOFOLLOW: a
    link planted there is refused, not a way to create or truncate a file elsewhere."""
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
    # MLflow logs a failed write with its SQL and stack traces; StoreError says it in one line
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.CRITICAL)
    with store_lock(uri):  # the client's construction creates and migrates the store
        if uri.startswith("sqlite:///"):
            check_sqlite_usable(uri)  # after the lock: a migration under way is not a fault
            create_whole(uri)
        client = mlflow.MlflowClient(uri)
        client.search_experiments(max_results=1)
    return client


def create_whole(uri: str) -> None:
    """Create a new sqlite store under a temporary name and rename it into place once MLflow has
    made its whole schema: a kill meanwhile would leave a half-made store. Under :func:`store_lock`,
    so a temporary file found is one a kill left behind."""
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
    """A migrated sqlite store (``$FEDLGR_EMPTY_STORE``, else in the cache folder) copied for every
    new store, as migrating is slow; None where it cannot be made. No Default experiment: MLflow
    roots its artifacts in the working folder of the process that creates it."""
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
    """The innermost reason, one line (an MLflow error wraps SQLAlchemy's wrapping sqlite's)."""
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
