"""The ``fedlgr`` command: one console script with verbs, each a typed function (typer). An
error the user can fix is one line and exit status 1, a command line that does not parse 2."""

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
from pathlib import Path
from types import SimpleNamespace
from typing import Annotated

import click
import typer

from fedlgr import __version__
from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.address_space import out_of_address_space, torch_guarded
from fedlgr.shell.cli import data, demo, deploy, pretrain, report, run, sweep
from fedlgr.shell.machine import tune_allocator
from fedlgr.shell.signals import Terminated, quiet_exit
from fedlgr.shell.tracking.uri import mask_password

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
        if err.ctx is not None:
            print(err.ctx.get_usage(), file=sys.stderr)
        message = err.format_message()
        if isinstance(err, click.NoSuchOption):  # argparse's words, as before
            message = f"unrecognized arguments: {err.option_name}"
        print(f"fedlgr: error: {message}", file=sys.stderr)
        raise SystemExit(err.exit_code) from None
    call = functools.partial(ctx.invoke, ctx.command.callback, **params)
    return SimpleNamespace(verb=ctx.command_path.split()[1], run=call, **params)


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
    except (FedlgrError, MemoryError, ImportError, OSError, RuntimeError) as err:
        problem = out_of_address_space(err, args.verb) or _symlink_loop(err)
        if problem is None and not isinstance(err, FedlgrError):
            raise
        print(f"fedlgr: error: {problem or err}", file=sys.stderr)
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
        # Exit fast: the teardown's garbage collections, seconds after a sweep, skip its
        # objects (gc.freeze), and what it says of objects it did not free (nanobind's leak
        # report) goes nowhere, so fedlgr's line stays the last.
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        gc.freeze()
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), 2)
    return code


def check_repeats(args: SimpleNamespace) -> None:
    """Refuse a setting given twice with two values, or ``--tracking-uri`` with another
    ``tracking.uri=``; one value spelled twice passes. A sweep's workers, given both by the
    sweep, are not checked."""
    given: dict[str, tuple[str, object]] = {}
    for item in getattr(args, "items", None) or getattr(args, "overrides", None) or []:
        key, is_override, text = item.partition("=")
        if not is_override:
            continue
        key, value = key.strip(), _value(text)
        if key in given and not _same(key, given[key][1], value):
            first, second = mask_password(given[key][0]), mask_password(item)
            raise FedlgrError(
                f"command line: {first!r} and {second!r} both set {key}; give one of them"
            )
        given.setdefault(key, (item, value))
    uri = getattr(args, "tracking_uri", None)
    override, value = given.get("tracking.uri", (None, None))
    worker = getattr(args, "worker_id", 0)
    if uri and value is not None and not worker and not _same("tracking.uri", uri, value):
        raise FedlgrError(
            f"command line: --tracking-uri {mask_password(uri)} and "
            f"{mask_password(override)!r} name two tracking stores; give one of them"
        )


def _value(text: str) -> object:
    """An override's value as OmegaConf reads it (``01`` is 1, `` x`` is ``x``)."""
    from omegaconf import OmegaConf  # lazy: omegaconf, only when a verb runs

    try:
        return OmegaConf.to_container(OmegaConf.from_dotlist([f"v={text}"]))["v"]
    except Exception:  # said with its reason when the config is loaded
        return text


def _same(key: str, first: object, second: object) -> bool:
    """Whether two values of ``key`` are one: equal, or one sqlite file by two paths."""
    if first == second:
        return True
    if key == "tracking.uri" and isinstance(first, str) and isinstance(second, str):
        paths = [
            u.removeprefix("sqlite:///") for u in (first, second) if u.startswith("sqlite:///")
        ]
        return len(paths) == 2 and Path(paths[0]).resolve() == Path(paths[1]).resolve()
    return False


if __name__ == "__main__":
    sys.exit(main())
