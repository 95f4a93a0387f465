"""The ``fedlgr`` command: one console script with verbs.

Each verb is a module of this package that declares its options (``add_parser``) next to
the thin function that runs it, and imports what is heavy (torch, MLflow, Optuna, Flower)
only when it runs, so ``fedlgr --help`` answers without loading torch. This module
assembles the verbs and dispatches to them. Errors the user can fix
(:class:`fedlgr.errors.FedlgrError`) are printed as one line and exit with status 1.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import logging
import os
import re
import signal
import sys
import warnings

from fedlgr import __version__
from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.address_space import out_of_address_space, torch_guarded
from fedlgr.shell.cli import data, demo, deploy, pretrain, report, run, sweep
from fedlgr.shell.cli.overrides import check_repeats
from fedlgr.shell.cli.parser import Parser
from fedlgr.shell.machine import tune_allocator
from fedlgr.shell.signals import Terminated, quiet_exit

VERBS = (demo, run, report, sweep, pretrain, data, deploy)  # in the order --help lists them


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="fedlgr",
        description="Federated (continual) learning of socially appropriate robot behaviours: "
        "FedRoot, FedLGR and baselines on MANNERS-DB or a synthetic living room.",
    )
    parser.add_argument("--version", action="version", version=f"fedlgr {__version__}")
    verbs = parser.add_subparsers(dest="verb", metavar="VERB", required=True)
    for verb in VERBS:
        verb.add_parser(verbs)
    return parser


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    """Options may come between and after overrides (``run CONFIG --tracking-uri U a=1``):
    argparse stops collecting a verb's ``key=value`` list at the first option, so the rest
    are taken back here (its intermixed parsing does not support sub-commands)."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    listed = next((name for name in ("items", "overrides") if hasattr(args, name)), None)
    stray = [e for e in extra if listed is None or "=" not in e or e.startswith("-")]
    if stray:
        parser.error(f"unrecognized arguments: {' '.join(stray)}")
    if extra:
        getattr(args, listed).extend(extra)
    if isinstance(getattr(args, "resume", None), str) and "=" in args.resume:
        args.items.append(args.resume)  # `--resume key=value`: a bare --resume, then an override
        args.resume = True
    return args


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
            return args.run(args) or 0
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
    """Say that a Ctrl-C or a SIGTERM/SIGHUP stopped the verb, and return the shell's exit
    status for it (128 + the signal). ``exits``: the process is fedlgr and exits now (not a
    caller's, e.g. a test's)."""
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
    """After an interrupt everything is recorded and the last line printed; what is left
    is memory the exit returns. The garbage collections of the interpreter's teardown took
    4-5 s after a sweep (a SIGTERM obeyed in ~9 s; 1.9 s without them): its objects are
    left out of them (``gc.freeze``), and what the teardown then says of objects it did not
    free (nanobind's leak report for triton's types) goes nowhere - fedlgr's line was the
    last."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    gc.freeze()
    with contextlib.suppress(OSError):
        quiet = os.open(os.devnull, os.O_WRONLY)
        os.dup2(quiet, 2)


if __name__ == "__main__":
    sys.exit(main())
