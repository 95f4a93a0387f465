"""The ``fedlgr`` command: one console script with verbs.

Each verb is a thin function in this package that imports what it needs when it runs,
so ``fedlgr --help`` answers without loading torch. Errors the user can fix
(:class:`fedlgr.errors.FedlgrError`) are printed as one line and exit with status 1.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import re
import signal
import sys
import warnings
from pathlib import Path

from fedlgr import __version__
from fedlgr.errors import FedlgrError

DEFAULT_DATA = Path("data/manners-synth")


def _crop(text: str) -> tuple[int | None, ...]:
    """``--crop 295,,1313,`` -> (295, None, 1313, None)."""
    parts = text.split(",")
    if len(parts) != 4:
        raise argparse.ArgumentTypeError(
            "expected LEFT,TOP,RIGHT,BOTTOM (leave one empty for an edge)"
        )
    try:
        return tuple(int(p) if p.strip() else None for p in parts)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"not a pixel position: {err}") from None


class HelpFormatter(argparse.HelpFormatter):
    """Every option's default in its help (argparse's ``ArgumentDefaultsHelpFormatter``
    without the noise of ``None``, ``False`` and ``[]``), and paragraphs of a description or
    epilog kept apart, and one that holds lines indented by two spaces (a listing) kept as
    written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            "%(default)" in text
            or default is None
            or default is False
            or default == []
            or default == argparse.SUPPRESS
            or not (action.option_strings or action.nargs in ("?", "*"))
        ):
            return text
        return f"{text} (default: %(default)s)"

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        blocks = []
        for block in text.split("\n\n"):
            if block.startswith("  ") or "\n  " in block:
                blocks.append("\n".join(indent + line for line in block.splitlines()))
            else:
                blocks.append(super()._fill_text(block, width, indent))
        return "\n\n".join(blocks)


class Parser(argparse.ArgumentParser):
    """An argument parser with :class:`HelpFormatter`, for the verbs too (sub-parsers are
    made of their parent's class)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)


def shipped_sweeps() -> list[tuple[str, str]]:
    """``(name, what it sweeps)`` for each YAML file in ``sweeps/`` (the checkout's or the
    installed package's): its ``description:``, else its header comment's first line if
    short. Plain text reading, no YAML parser: ``fedlgr --help`` builds this too."""
    from fedlgr.shell.config import SWEEPS_DIR

    listing = []
    for path in sorted(SWEEPS_DIR.glob("*.yaml")):
        lines = path.read_text(encoding="utf-8").splitlines()
        described = [ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("description:")]
        header = lines[0].lstrip("# ").strip() if lines and lines[0].startswith("#") else ""
        text = (described or [""])[0].strip("\"'") or (header if len(header) <= 72 else "")
        listing.append((path.stem, text))
    return listing


def _sweep_epilog() -> str:
    from fedlgr.shell.config import SWEEPS_DIR

    listing = shipped_sweeps()
    if not listing:
        return ""
    width = max(len(name) for name, _ in listing)
    lines = [f"  {name.ljust(width)}  {text}".rstrip() for name, text in listing]
    return f"shipped sweeps (in {SWEEPS_DIR}):\n" + "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="fedlgr",
        description="Federated (continual) learning of socially appropriate robot behaviours: "
        "FedRoot, FedLGR and baselines on MANNERS-DB or a synthetic living room.",
    )
    parser.add_argument("--version", action="version", version=f"fedlgr {__version__}")
    verbs = parser.add_subparsers(dest="verb", metavar="VERB", required=True)

    demo = verbs.add_parser(
        "demo",
        help="the main job: FedAvg vs FedRootAvg on the embedded synthetic data",
        description="Synthesise the living room if absent, then train FedAvg and FedRootAvg on "
        "it (conf/experiment/demo.yaml), tracked in MLflow, and print a comparison table.",
    )
    demo.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")
    demo.add_argument("--data", type=Path, default=DEFAULT_DATA, help="dataset folder")
    demo.add_argument("--scenes", type=int, default=1000, help="scenes to synthesise if absent")
    demo.add_argument("--seed", type=int, default=0, help="seed of the data and the runs")
    demo.add_argument(
        "--tracking-uri",
        help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or sqlite:///mlflow.db)",
    )
    demo.add_argument(
        "--fcl",
        action="store_true",
        help="show forgetting instead: FedRoot "
        "without a CL method vs FedLGR, circle then arrow (see --modality)",
    )
    demo.add_argument(
        "--modality",
        choices=["features", "image"],
        default="features",
        help="--fcl: the descriptors (MLP root, about 35 s) or the images "
        "(a root pretrained once, about 4 minutes)",
    )
    demo.add_argument(
        "--pretrain-scenes",
        type=int,
        default=2000,
        help="--fcl: scenes (of another seed) the root is pretrained on",
    )
    demo.add_argument(
        "--pretrain-images",
        type=int,
        default=16000,
        help="--fcl: augmented images the root is pretrained on",
    )
    demo.set_defaults(run="fedlgr.shell.cli.demo:demo")

    run = verbs.add_parser(
        "run",
        help="run one experiment from a config and key=value overrides",
        description="Run one federated experiment, tracked in MLflow. CONFIG is a YAML file "
        "(e.g. conf/experiment/table1/clients2_noaug.yaml); overrides are key=value, e.g. "
        "method=FedRootAvg data.path=/path/to/manners-db federated.rounds=5.",
    )
    run.add_argument(
        "items",
        nargs="*",
        metavar="CONFIG|key=value",
        help="a config file (a path, or a name in conf/ such as debug/fast.yaml), then "
        "overrides such as federated.rounds=5 (without a config: the defaults)",
    )
    run.add_argument(
        "--print-config",
        action="store_true",
        help="print the resolved config (file, includes and overrides) as YAML and exit "
        "without running; settings resolved at start (runtime.threads, runtime.concurrency, "
        "...) show as given",
    )
    run.add_argument(
        "--tracking-uri",
        help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI "
        "or sqlite:///mlflow.db with artifacts in mlruns/)",
    )
    run.add_argument(
        "--resume",
        nargs="?",
        const=True,
        metavar="RUN_ID",
        help="continue an interrupted run from its last checkpoint, in the same MLflow run: "
        "RUN_ID, or (without one) the latest unfinished run of the same config",
    )
    run.set_defaults(run="fedlgr.shell.cli.run:run")

    rep = verbs.add_parser(
        "report",
        help="the paper's tables (Markdown, LaTeX, CSV) and plots from the runs in MLflow",
        description="Read the finished runs of an experiment (or the trials of a sweep) from "
        "MLflow and write Tables I-IV (tableN.md/.tex/.csv: FL and FCL results, FL and FCL "
        "costs) and PNG plots to --out, then log that folder to MLflow (a run named 'report', "
        "or the reported study's parent run) under report/. A cell averages the runs of one "
        "method and setting whose settings differ only in their seeds (seed, data.seed); a "
        "repeated seed counts once (the newest run); runs of one cell with other settings are "
        "refused: narrow them with --where.",
    )
    rep.add_argument(
        "--experiment",
        help="MLflow experiment (default: tracking.experiment's default, unless --sweep is given)",
    )
    rep.add_argument(
        "--sweep",
        help="only the trials of this sweep (tag sweep=NAME), in every experiment or in "
        "--experiment",
    )
    rep.add_argument(
        "--study",
        help="with --sweep: the study to report, by name or parent run id (default: the "
        "newest study of the sweep in this store)",
    )
    rep.add_argument(
        "--where",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="only runs with this setting, as MLflow holds it (e.g. federated.rounds=20; "
        "repeatable)",
    )
    rep.add_argument(
        "--out",
        type=Path,
        help="output folder (default: reports/EXPERIMENT or reports/sweeps/SWEEP/STUDY-RUNID, "
        "with a sub-folder for --dataset/--modality/--where)",
    )
    rep.add_argument(
        "--tracking-uri",
        help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or sqlite:///mlflow.db)",
    )
    rep.add_argument("--dataset", help="only runs on this dataset (tag dataset, e.g. synthetic)")
    rep.add_argument("--modality", choices=["image", "features"], help="only runs of this modality")
    rep.add_argument("--no-log", action="store_true", help="write the files but log nothing")
    rep.set_defaults(run="fedlgr.shell.cli.report:report")

    sweep = verbs.add_parser(
        "sweep",
        epilog=_sweep_epilog(),
        help="run or resume an Optuna sweep (grid or TPE) of experiments",
        description="Run the trials of SWEEP (a file in sweeps/, e.g. sweeps/ewc.yaml or just "
        "ewc) as an Optuna study, each trial an experiment tracked in MLflow under one parent "
        "run. Launching it again resumes the study; --workers N (or launches elsewhere on the "
        "same --storage) work on it in parallel. Overrides apply to every trial, e.g. "
        "data.path=/path/to/manners-db.",
    )
    sweep.add_argument("sweep", help="sweep file or name (the shipped ones are listed below)")
    sweep.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")
    sweep.add_argument(
        "--storage",
        default="sqlite:///optuna.db",
        help="Optuna RDB storage URL (default: %(default)s; a PostgreSQL/MySQL URL for several "
        "machines)",
    )
    sweep.add_argument("--study", help="study name (default: the sweep's name)")
    sweep.add_argument(
        "--settings-changed",
        action="store_true",
        help="go on with a study started with other settings (the sweep file or overrides, "
        "e.g. a dataset that moved); its finished trials count as they are",
    )
    sweep.add_argument("--workers", type=int, default=1, help="processes on this machine")
    sweep.add_argument(
        "--tracking-uri",
        help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or sqlite:///mlflow.db)",
    )
    sweep.add_argument(
        "--heartbeat",
        type=int,
        default=None,
        help="seconds between a worker's heartbeats; a trial silent for two is retried "
        "(default: the sweep file's heartbeat_s)",
    )
    sweep.add_argument("--worker-id", type=int, default=0, help=argparse.SUPPRESS)
    sweep.set_defaults(run="fedlgr.shell.cli.sweep:sweep")

    pre = verbs.add_parser(
        "pretrain",
        help="pretrain a MobileNetV2 root on scene descriptors (no labels), offline",
        description="Train a MobileNetV2 root to predict each scene's 27 descriptors and 2 mode "
        "flags from its image (no appropriateness labels) and save it for model.weights=FILE: an "
        "offline stand-in for ImageNet weights. Use a dataset other than the one you evaluate on, "
        "e.g. fedlgr data synth --out data/pretrain-synth --seed 1000 --scenes 2000.",
    )
    pre.add_argument("--data", type=Path, required=True, help="a MANNERS-DB-layout folder")
    pre.add_argument("--out", type=Path, required=True, help="the root's state-dict file to write")
    pre.add_argument("--width", type=float, default=1.0, help="MobileNetV2 width multiplier")
    pre.add_argument("--images", type=int, default=16000, help="augmented images to train on")
    pre.add_argument("--size", type=int, default=128, help="image width and height in pixels")
    pre.add_argument(
        "--crop", type=_crop, default=None, help="LEFT,TOP,RIGHT,BOTTOM before resizing"
    )
    pre.add_argument("--seed", type=int, default=0, help="seed of the augmentation and the root")
    pre.set_defaults(run="fedlgr.shell.cli.pretrain:pretrain")

    data = verbs.add_parser("data", help="create, inspect and check datasets")
    data_verbs = data.add_subparsers(dest="data_verb", metavar="VERB", required=True)
    synth = data_verbs.add_parser(
        "synth", help="write a synthetic living room in the MANNERS-DB layout"
    )
    synth.add_argument("--out", type=Path, required=True, help="folder to write")
    synth.add_argument("--scenes", type=int, default=1000, help="scenes to write")
    synth.add_argument("--seed", type=int, default=0, help="seed of the scenes and ratings")
    synth.add_argument("--size", type=int, default=128, help="image width and height in pixels")
    synth.add_argument("--force", action="store_true", help="overwrite a non-empty folder")
    synth.set_defaults(run="fedlgr.shell.cli.data:synth")

    show = data_verbs.add_parser("show", help="contact sheet of a few scenes with their labels")
    show.add_argument("folder", type=Path, help="a MANNERS-DB-layout folder")
    show.add_argument(
        "--out", type=Path, default=Path("contact_sheet.png"), help="the PNG file to write"
    )
    show.add_argument("--scenes", type=int, default=8, help="scenes on the sheet")
    show.add_argument("--seed", type=int, default=0, help="seed of the choice of scenes")
    show.add_argument(
        "--crop", type=_crop, default=None, help="LEFT,TOP,RIGHT,BOTTOM before resizing"
    )
    show.set_defaults(run="fedlgr.shell.cli.data:show")

    check = data_verbs.add_parser("check", help="validate a dataset folder and summarise it")
    check.add_argument("folder", type=Path, help="a MANNERS-DB-layout folder")
    check.add_argument(
        "--modality",
        choices=["image", "features"],
        default="image",
        help="check the images too, or the CSV's descriptors alone",
    )
    check.add_argument(
        "--size", type=int, default=128, help="image width and height to decode to, in pixels"
    )
    check.add_argument(
        "--crop", type=_crop, default=None, help="LEFT,TOP,RIGHT,BOTTOM before resizing"
    )
    check.add_argument(
        "--skip-bad-images",
        action="store_true",
        help="skip (with a warning) scenes whose image is missing or corrupt instead of failing",
    )
    check.add_argument("--clients", type=int, default=2, help="clients of the split shown")
    check.set_defaults(run="fedlgr.shell.cli.data:check")

    from fedlgr.shell.cli.deploy_args import (
        add_parser as add_deploy,  # argparse only: --help stays fast
    )

    add_deploy(verbs)
    return parser


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    return f"fedlgr: warning: {message}\n"


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


def _check_repeats(args: argparse.Namespace) -> None:
    """Refuse a setting given twice with two values, or ``--tracking-uri`` with another
    ``tracking.uri=``: the last one won and the other was dropped without a word (the tenth
    fault sweep, d101, d145, d146, d163). One value spelled twice (``seed=1 'seed =01'``,
    one sqlite file by two paths) and ``tracking.uri=null`` pass (the eleventh, d178, e62,
    e64, e73, e150, e152). A sweep's worker processes are given both by the sweep that
    starts them, and are not checked."""
    from fedlgr.shell.tracking.server import mask_password

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
    from omegaconf import OmegaConf

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


def main(argv: list[str] | None = None) -> int:
    # MLflow 3 reports usage to its makers on every run unless told not to.
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    args = parse(argv)
    module_name, func_name = args.run.split(":")
    standard_format, warnings.formatwarning = warnings.formatwarning, _one_line_warning
    try:
        import importlib

        from fedlgr.shell.machine import tune_allocator

        tune_allocator()
        if getattr(args, "tracking_uri", None) == "":  # '' would fall back to the default
            raise FedlgrError("--tracking-uri '': empty; give a URI, or leave it out")
        _check_repeats(args)
        # MLflow announces its sqlite schema set-up at INFO on every new store: not news.
        logging.getLogger("mlflow.store.db.utils").setLevel(logging.WARNING)
        verb = getattr(importlib.import_module(module_name), func_name)
        return verb(args) or 0
    except FedlgrError as err:
        print(f"fedlgr: error: {err}", file=sys.stderr)
        return 1
    except RuntimeError as err:
        # Python 3.11's pathlib says a symbolic link that loops (a config, data.path, a
        # store's path ...) this way, where 3.13 raises OSError (the seventh fault sweep, v27)
        loop = re.fullmatch(r"Symlink loop from '(.*)'", str(err))
        if loop is None:
            raise
        print(f"fedlgr: error: {loop.group(1)}: a symbolic link that loops", file=sys.stderr)
        return 1
    except KeyboardInterrupt as err:
        from fedlgr.shell.signals import Terminated, quiet_exit

        terminated = isinstance(err, Terminated)
        name = str(err) if terminated and str(err) in ("SIGTERM", "SIGHUP") else "SIGTERM"
        code = 128 + (signal.Signals[name] if terminated else signal.SIGINT)  # the shell's way
        if argv is None:  # the process is fedlgr and exits now (not a caller's, e.g. a test's)
            quiet_exit(code)  # a second Ctrl-C would print a traceback from an atexit hook
        hint = "".join(f"; {note}" for note in getattr(err, "__notes__", ()))
        print(
            f"fedlgr: {f'terminated ({name})' if terminated else 'interrupted'}{hint}",
            file=sys.stderr,
        )
        if argv is None:
            _leave_quickly()
        return code
    finally:
        warnings.formatwarning = standard_format


def _leave_quickly() -> None:
    """After an interrupt everything is recorded and the last line printed; what is left
    is memory the exit returns. The garbage collections of the interpreter's teardown took
    4-5 s after a sweep (a SIGTERM obeyed in ~9 s; 1.9 s without them): its objects are
    left out of them (``gc.freeze``), and what the teardown then says of objects it did not
    free (nanobind's leak report for triton's types) goes nowhere - fedlgr's line was the
    last."""
    import gc

    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    gc.freeze()
    with contextlib.suppress(OSError):
        quiet = os.open(os.devnull, os.O_WRONLY)
        os.dup2(quiet, 2)


if __name__ == "__main__":
    sys.exit(main())
