"""The ``fedlgr`` command: one console script with verbs, each a typed function (typer).

A verb imports what is heavy only when it runs, so ``fedlgr --help`` answers without torch; an
error the user can fix is one line and exit status 1, a command line that does not parse 2.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import logging
import os
import re
import signal
import sys
import warnings
from types import SimpleNamespace
from typing import Annotated, NoReturn

import click
import typer

from fedlgr import __version__
from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.address_space import out_of_address_space, torch_guarded
from fedlgr.shell.cli import data, demo, deploy, pretrain, report, run, sweep
from fedlgr.shell.cli.overrides import check_repeats
from fedlgr.shell.machine import tune_allocator
from fedlgr.shell.signals import Terminated, quiet_exit

VERBS = (demo, run, report, sweep, pretrain, data, deploy)  # in the order --help lists them

app = typer.Typer(
    help="Federated (continual) learning of socially appropriate robot behaviours: FedRoot, "
    "FedLGR and baselines on MANNERS-DB or a synthetic living room.",
    context_settings={"help_option_names": ["-h", "--help"]},
    add_completion=False,
)
for module in VERBS:
    app.add_typer(module.app)  # nameless: its commands join fedlgr's


def _version(asked: bool) -> None:
    if asked:
        print(f"fedlgr {__version__}")
        raise typer.Exit()


@app.callback()
def fedlgr(
    version: Annotated[
        bool,
        typer.Option("--version", callback=_version, is_eager=True, help="print the version"),
    ] = False,
) -> None:
    """The verbs' group: its one option, ``--version``, answers before any verb."""


@functools.cache
def command() -> click.Group:
    return typer.main.get_command(app)


def parse(argv: list[str] | None = None) -> SimpleNamespace:
    """The verb of ``argv`` (``verb``: its name, ``run``: its function, given its arguments)
    and its arguments by name; ``--help`` and ``--version`` exit 0, a usage error 2. Overrides
    may come anywhere; ``--resume key=value`` is a bare ``--resume``, then an override."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        ctx = command().invoke(command().make_context("fedlgr", argv))
        params, listed = dict(ctx.params), []
        for name in {"items", "overrides"} & set(params):
            listed = params[name] = list(params[name])
        if isinstance(params.get("resume"), str) and "=" in params["resume"]:
            listed.append(params["resume"])
            params["resume"] = True
        stray = [i for i in listed if "=" not in i][int(ctx.command_path == "fedlgr run") :]
        if stray:  # an override is key=value; fedlgr run's first other item is its config
            raise click.UsageError(f"unrecognized arguments: {' '.join(stray)}", ctx)
    except click.exceptions.Exit as done:
        raise SystemExit(done.exit_code) from None
    except click.UsageError as err:
        _usage_error(err)
    call = functools.partial(ctx.invoke, ctx.command.callback, **params)
    return SimpleNamespace(verb=ctx.command_path.split()[1], run=call, **params)


def _usage_error(err: click.UsageError) -> NoReturn:
    if err.ctx is not None:
        print(err.ctx.get_usage(), file=sys.stderr)
    message = err.format_message()
    if isinstance(err, click.NoSuchOption):  # argparse's words, as before
        message = f"unrecognized arguments: {err.option_name}"
    print(f"fedlgr: error: {message}", file=sys.stderr)
    raise SystemExit(err.exit_code)


def main(argv: list[str] | None = None) -> int:
    # MLflow 3 reports usage to its makers on every run unless told not to.
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    args = parse(argv)
    standard_format, warnings.formatwarning = warnings.formatwarning, _one_line_warning
    try:
        tune_allocator()
        if getattr(args, "tracking_uri", None) == "":  # '' would fall back to the default
            raise FedlgrError("--tracking-uri '': empty; give a URI, or leave it out")
        check_repeats(args)
        # MLflow announces its sqlite schema set-up at INFO on every new store: not news.
        logging.getLogger("mlflow.store.db.utils").setLevel(logging.WARNING)
        with torch_guarded(args.verb):  # under `ulimit -v`: room for torch, or one line
            return args.run() or 0
    except FedlgrError as err:
        print(f"fedlgr: error: {out_of_address_space(err, args.verb) or err}", file=sys.stderr)
        return 1
    except (MemoryError, ImportError, OSError, RuntimeError) as err:
        problem = out_of_address_space(err, args.verb) or _symlink_loop(err)
        if problem is None:
            raise
        print(f"fedlgr: error: {problem}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as err:
        return _interrupted(err, exits=argv is None)
    finally:
        warnings.formatwarning = standard_format


def _symlink_loop(err: BaseException) -> str | None:
    """Python 3.11's pathlib says a symbolic link that loops (a config, data.path, a
    store's path ...) with a RuntimeError, where 3.13 raises OSError: one line all the same."""
    if not isinstance(err, RuntimeError):
        return None
    loop = re.fullmatch(r"Symlink loop from '(.*)'", str(err))
    return None if loop is None else f"{loop.group(1)}: a symbolic link that loops"


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    return f"fedlgr: warning: {message}\n"


def _interrupted(err: KeyboardInterrupt, exits: bool) -> int:
    """Say that a Ctrl-C or a SIGTERM/SIGHUP stopped the verb; the shell's exit status for it
    (128 + the signal). ``exits``: the process is fedlgr's and exits now (not a test's)."""
    terminated = isinstance(err, Terminated)
    name = str(err) if terminated and str(err) in ("SIGTERM", "SIGHUP") else "SIGTERM"
    code = 128 + (signal.Signals[name] if terminated else signal.SIGINT)  # the shell's way
    if exits:
        quiet_exit(code)  # a second Ctrl-C would print a traceback from an atexit hook
    hint = "".join(f"; {note}" for note in getattr(err, "__notes__", ()))
    print(
        f"fedlgr: {f'terminated ({name})' if terminated else 'interrupted'}{hint}",
        file=sys.stderr,
    )
    if exits:
        _leave_quickly()
    return code


def _leave_quickly() -> None:
    """Exit fast after an interrupt: the teardown's garbage collections, seconds after a sweep,
    skip its objects (``gc.freeze``), and what it says of objects it did not free (nanobind's
    leak report) goes nowhere, so fedlgr's line stays the last."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    gc.freeze()
    with contextlib.suppress(OSError):
        quiet = os.open(os.devnull, os.O_WRONLY)
        os.dup2(quiet, 2)


if __name__ == "__main__":
    sys.exit(main())
