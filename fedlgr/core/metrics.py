"""What a round measures, by name: every score and every cost is defined once, here.

A client's scores and its round's costs travel as ``key -> value`` mappings keyed by
their MLflow key (``test/rmse``, ``task/circle/pcc``, ``cost/cpu_s``): from the meter that
measures them (:mod:`fedlgr.core.meters`) through the messages and the Flower wire to
the round's record (:class:`fedlgr.core.records.RoundLog`), results.csv, MLflow, the
console and the reports, each of which iterates these definitions. So a new score is its
definition here and its function in :mod:`fedlgr.core.meters.scores`; a new cost is its
definition here and the line that measures it. This module imports nothing heavy: the
config checks and the reports read it without torch.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from fedlgr.core.data.columns import LABEL_SHORT_NAMES

Figures = dict[str, float]  # MLflow key -> value


# The bounds of an error and of a correlation (Score.bounds).
ERROR = (0.0, math.inf)
CORRELATION = (-1.0, 1.0)


@dataclass(frozen=True)
class Score:
    """A score of a model's outputs on test scenes: computed per action over the whole test
    set (not per batch), reported as the mean over the 8 actions."""

    name: str  # test/<name>, task/<task>/<name>, server/test/<name>
    label: str  # its heading in the console, the reports' tables and plots ("RMSE")
    higher_is_better: bool
    per_action: str  # its per-action figure: test/<per_action>/<action>
    about: str  # what it is, in one line
    bounds: tuple[float, float]  # the values it can take: a client's report outside is refused
    headline: bool = True  # a researcher compares runs by it: runs table, curves, plots

    @property
    def arrow(self) -> str:
        """How a heading says which way is better: ▲ higher, ▼ lower."""
        return "▲" if self.higher_is_better else "▼"


SCORES: tuple[Score, ...] = (
    Score("loss", "loss", False, "mse", "mean squared error, averaged over the 8 actions",
          ERROR, headline=False),  # the square of the RMSE: nothing more to compare runs by
    Score("rmse", "RMSE", False, "rmse", "root mean squared error per action, averaged", ERROR),
    Score("pcc", "PCC", True, "pcc", "Pearson correlation per action (constant: 0), averaged",
          CORRELATION),
    Score("ccc", "CCC", True, "ccc", "Lin's concordance correlation per action, averaged",
          CORRELATION),
)  # fmt: skip
SCORE_NAMES = tuple(s.name for s in SCORES)


def headline_scores() -> tuple[Score, ...]:
    """The scores runs are compared by, in :data:`SCORES`' order: every writer's columns,
    curves and plots. Read from SCORES at each call, so no writer holds a stale copy."""
    return tuple(s for s in SCORES if s.headline)


# The order MLflow lists a run's scores in: the headline scores, then the others.
HEADLINE = tuple(f"test/{s.name}" for s in sorted(SCORES, key=lambda s: not s.headline))


@dataclass(frozen=True)
class Cost:
    """What one client's round cost, measured on the client (or, for bytes, counted by the
    server), per client per round."""

    key: str  # its MLflow key
    # How two pieces of one client's work in a round add up (its training and its task
    # end): "sum", "max", or "mean" weighted by their wall seconds (absent unless both
    # pieces have it).
    combine: str = "sum"
    # Work done for several clients at once (clients stacked into one model) is given out
    # in proportion to their samples (True), or is every one's (False: the wall time).
    shared_out: bool = False
    label: str = ""  # its row in the reports' cost tables ("": none)
    scale: float = 1.0  # ... shown as value x scale
    decimals: int = 2
    summary: str = ""  # its column in a run's console summary ("": none)


COSTS: tuple[Cost, ...] = (
    Cost("cost/cpu_s", "sum", True, "CPU usage (s)", summary="CPU s/round"),
    Cost("cost/wall_s", "sum", False, "Wall time (s)", summary="wall s/round"),
    Cost("cost/gpu_util", "mean", False, "GPU usage (%)"),  # NVML, device-wide
    Cost("cost/gpu_mem_mb", "max"),  # torch's allocator peak
    Cost("cost/gpu_s", "sum", True),  # the span of the client's work on its CUDA stream
    Cost("cost/bytes_up", label="Upload (MB)", scale=1e-6, decimals=3, summary="upload/round"),
    Cost("cost/bytes_down"),
    # torch's FlopCounterMode on the round's first batch, x the samples of the round
    Cost("cost/gflops", label="Training (GFLOPs)", decimals=3, summary="GFLOPs/round"),
)
COST_KEYS = tuple(c.key for c in COSTS)
_COST = {c.key: c for c in COSTS}

# What a client's local training reports besides its costs: its mean task loss over the
# round and the samples it trained on (all epochs, rehearsal included).
TRAINING = ("train/loss", "train/samples")


def score_keys(prefix: str, per_action: bool = False) -> list[str]:
    """``prefix/<score>`` for every score (``test/rmse``), then, with ``per_action``, every
    score's per-action figure (``test/rmse/vacuum``)."""
    keys = [f"{prefix}/{s.name}" for s in SCORES]
    if per_action:
        keys += [f"{prefix}/{s.per_action}/{a}" for s in SCORES for a in LABEL_SHORT_NAMES]
    return keys


def round_keys(tasks: Iterable[str], plugin_keys: Iterable[str] = ()) -> list[str]:
    """Every figure of a client's row in a round, in results.csv's column order: the scores
    on every task seen so far (per action too), each task's scores (FCL: ``tasks`` other
    than ``["all"]``), the training figures, the costs, what the plugins measure."""
    keys = score_keys("test", per_action=True)
    tasks = list(tasks)
    if tasks != ["all"]:
        for task in tasks:
            keys += score_keys(f"task/{task}")
    return keys + list(TRAINING) + list(COST_KEYS) + list(plugin_keys)


def column(key: str) -> str:
    """A key's results.csv column: ``test/rmse/vacuum`` -> ``test_rmse_vacuum``,
    ``cost/cpu_s`` -> ``cpu_s``, ``lgr/fd_latent`` -> ``lgr_fd_latent``."""
    return key.removeprefix("cost/").replace("/", "_")


def client_key(key: str, client: int) -> str:
    """The MLflow key of ``key`` for one client: ``test/pcc/vacuum`` ->
    ``test/client3/pcc/vacuum`` (the family first, then the client)."""
    family, _, rest = key.partition("/")
    return f"{family}/client{client}/{rest}"


def combine(first: Mapping[str, float], then: Mapping[str, float]) -> Figures:
    """Two pieces of one client's round (``first``, ``then``): costs added up by their
    rule, every other figure taken from the piece that has it (``then`` wins)."""
    out = {**first, **then}
    for key in set(first) | set(then):
        cost = _COST.get(key)
        if cost is None:
            continue
        a, b = first.get(key), then.get(key)
        if a is None or b is None:
            if cost.combine == "mean":  # a utilisation over part of the work says nothing
                out.pop(key)
            continue
        if cost.combine == "sum":
            out[key] = a + b
        elif cost.combine == "max":
            out[key] = max(a, b)
        else:  # the mean over both pieces, weighted by their wall seconds
            wa, wb = first["cost/wall_s"], then["cost/wall_s"]
            out[key] = (a * wa + b * wb) / max(wa + wb, 1e-9)
    return out


def shared_out(costs: Mapping[str, float], fraction: float) -> Figures:
    """One client's part of costs measured for several clients at once (stacked clients):
    ``fraction`` of the costs that are shared out, the others as they are."""
    return {
        k: v * fraction if (c := _COST.get(k)) is not None and c.shared_out else v
        for k, v in costs.items()
    }


def finite_or_none(value: float) -> float | None:
    """``value``, or None where it is not a number (a missing client's, a diverged run's)."""
    return None if value is None or math.isnan(value) else float(value)
