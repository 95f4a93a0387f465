"""User-facing errors.

Anything a user can fix (a bad CSV, a missing image, an impossible setting) raises a
:class:`FedlgrError` whose message names the file, row/stamp, column or setting at fault.
The command line prints such errors as one line and exits non-zero; any other exception
is a bug and keeps its traceback.
"""


class FedlgrError(Exception):
    """An error the user can fix; its message is printed as one line by the CLI."""


class DataError(FedlgrError):
    """Bad input data: CSV content, image files, folder layout."""


class ConfigError(FedlgrError):
    """An impossible or malformed setting."""


def join_problems(subject: str, problems: list[str], shown: int = 5) -> str:
    """One line that names ``subject`` and lists the first ``shown`` problems."""
    if len(problems) == 1:
        return f"{subject}: {problems[0]}"
    listed = "; ".join(problems[:shown])
    more = f"; ... and {len(problems) - shown} more" if len(problems) > shown else ""
    return f"{subject}: {len(problems)} problems: {listed}{more}"


def first_line(err: BaseException, limit: int | None = None) -> str:
    """The first line of ``err``'s message, stripped and cut to ``limit`` characters, or
    the name of its type when it has no message: how an error is quoted in one line."""
    text = str(err).strip()
    return (text.splitlines()[0].strip() if text else type(err).__name__)[:limit]


def exception_chain(err: BaseException | None):
    """``err``, then what caused it or was being handled when it was raised, each once."""
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        yield err
        err = err.__cause__ or err.__context__


def interrupt_in(err: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or SIGTERM (:class:`fedlgr.shell.signals.Terminated`) behind ``err``, if any:
    one that arrives while Optuna records a trial turns into Optuna 4's
    ``UnboundLocalError: ... 'updated_state'`` in ``_run_trial``, and a sweep stopped
    there would end in two tracebacks."""
    return next((e for e in exception_chain(err) if isinstance(e, KeyboardInterrupt)), None)
