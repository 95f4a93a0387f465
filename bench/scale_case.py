"""One case of ``bench/scale.py`` (issue 40) in a process of its own, so that its peak
memory is the run's alone. Run by that script with the python of the checkout it measures
(this one, or ``--reference``'s: whatever ``fedlgr`` that python imports); it reads one
JSON argument and prints one line, ``SCALE {...}``, with the run's figures.

The argument: ``config`` (a YAML path), ``overrides`` (``key=value``), ``optional`` (settings
that a checkout without them does not know: left out where ``load_config`` calls them
unknown, and named in the line's ``dropped``), ``checkpoints`` (the run's
``tracking.checkpoint_dir``), and ``warm``: only load the data (decoding the images into
the cache), run nothing.

The line: ``status`` ("ok", or "refused: <the error's first line>"), then per round the
wall time from the round's start to its ``on_round`` (training, evaluation, MLflow and the
checkpoint: what a user waits for), the process's CPU seconds in that time and the
runtime's own ``RoundLog.seconds``; the peak resident memory (``ru_maxrss``); where the
result has them (issue 40 on), each round's MLflow logging and checkpoint seconds and the
end's results.csv; the largest size the checkpoint folder reached (a finished run removes
it); the seconds before round 1 (imports, data, MLflow) and in all.
"""

from __future__ import annotations

import itertools
import json
import resource
import sys
import time
from pathlib import Path

import psutil

from fedlgr.errors import ConfigError, FedlgrError, first_line
from fedlgr.shell.config import load_config
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.run.experiment import run_experiment

PREFIX = "SCALE "


def main(argv: list[str]) -> int:
    spec = json.loads(argv[0])
    try:
        config, dropped = configure(spec["config"], spec["overrides"], spec.get("optional", []))
        if spec.get("warm"):
            load_scenes(config.data)
            emit({"status": "ok", "dropped": dropped})
            return 0
        clock = Clock(Path(spec["checkpoints"]))
        result = run_experiment(
            config,
            echo=lambda *args, **kwargs: None,
            on_start=clock.start,
            on_round=clock.round,
            show_runs=False,
        )
    except FedlgrError as err:  # a setting, the data or a store refused: one line says why
        emit({"status": f"refused: {first_line(err, 300)}"})
        return 0
    emit({"status": "ok", "dropped": dropped, **clock.figures(), **recording(result)})
    return 0


def configure(path: str, overrides: list[str], optional: list[str]):
    """The config, and the ``optional`` settings this checkout does not know (left out)."""
    kept, dropped = list(optional), []
    while True:
        try:
            return load_config(path, [*overrides, *kept]), dropped
        except ConfigError as err:
            unknown = [o for o in kept if f"{o.split('=')[0]}: unknown setting" in str(err)]
            if not unknown:
                raise
            kept.remove(unknown[0])
            dropped.append(unknown[0])


class Clock:
    """Each round's wall and CPU seconds (from the MLflow run's start to each round's
    ``on_round``, after its logging and checkpoint), and the checkpoint folder's size."""

    def __init__(self, checkpoints: Path):
        self.checkpoints = checkpoints
        self.marks: list[tuple[float, float]] = []
        self.checkpoint_bytes = 0
        self.setup_s: float | None = None

    def start(self, run_id: str) -> None:
        self.marks = [(time.perf_counter(), time.process_time())]
        self.setup_s = _alive()

    def round(self, round_: int, metrics: dict[str, float]) -> None:
        self.marks.append((time.perf_counter(), time.process_time()))
        self.checkpoint_bytes = max(self.checkpoint_bytes, size(self.checkpoints))

    def figures(self) -> dict:
        marks = self.marks
        return {
            "wall_s": [b[0] - a[0] for a, b in itertools.pairwise(marks)],
            "cpu_s": [b[1] - a[1] for a, b in itertools.pairwise(marks)],
            "setup_s": self.setup_s,
            "total_s": _alive(),
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "checkpoint_mib": self.checkpoint_bytes / 2**20,
        }


def recording(result) -> dict:
    """The rounds' own seconds, and what recording cost where the result says (issue 40)."""
    return {
        "round_s": [log.seconds for log in result.rounds],
        "tracking_s": getattr(result, "tracking_seconds", None),
        "checkpoint_s": getattr(result, "checkpoint_seconds", None),
        "results_s": getattr(result, "results_seconds", None),
    }


def size(folder: Path) -> int:
    """Bytes in the files under ``folder`` (0 if it is not there)."""
    if not folder.is_dir():
        return 0
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def _alive() -> float:
    """Seconds since this process started (imports included)."""
    return time.time() - psutil.Process().create_time()


def emit(figures: dict) -> None:
    print(PREFIX + json.dumps(figures), flush=True)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
