"""What one round records: a row of figures per client, by name.

Each client's row is a ``key -> value`` mapping (:mod:`fedlgr.core.metrics`: scores,
training figures, costs, what its plugins measured); :class:`RoundLog` lays the rows out
as a table whose columns are named by those keys - in results.csv's order, which
:func:`fedlgr.core.metrics.round_keys` gives - and a key it does not know is refused
rather than dropped.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from fedlgr.core.metrics import SCORES, client_key, column

# A client's score is an outlier of the round where it lies over this many scaled MADs
# (1.4826 MAD estimates a normal spread's sigma) from the median of the clients that count,
# and further than OUTLIER_FLOOR x max(1, |median|) from it: clients that score one model on
# one test set (FedAvg) agree to float rounding, MAD 0, and only a real difference counts.
OUTLIER_MADS = 3.0
OUTLIER_FLOOR = 1e-4


def is_score(key: str) -> bool:
    """Is ``key`` a score of a model on test scenes (``test/rmse``, ``task/circle/pcc``)?"""
    return key.startswith(("test/", "task/"))


def headline(values: np.ndarray, statistic: str = "mean") -> float | None:
    """The ``statistic`` of ``values`` that are not NaN (None if none are): ``mean``,
    ``median``, or ``trimmed B`` - the mean after leaving out the ``floor(B n)`` largest and
    smallest, as FedTrimmedAvg cuts the uploads."""
    present = np.sort(np.asarray(values, dtype=np.float64))
    present = present[~np.isnan(present)]
    if not present.size:
        return None
    if statistic == "median":
        return float(np.median(present))
    if statistic.startswith("trimmed "):
        cut = int(float(statistic.split()[1]) * present.size)
        present = present[cut : present.size - cut]
    return float(present.mean())


@dataclass(frozen=True)
class Field:
    """One number per client per round: its results.csv column and its MLflow key."""

    name: str
    key: str


def table(
    keys: list[str], rows: Mapping[int, Mapping[str, float]], clients: int, fill: float = math.nan
) -> np.ndarray:
    """``rows`` (client -> its figures) as a (clients x keys) float64 table: NaN where a
    figure was not measured, ``fill`` for the clients with no row. A figure whose key is
    not in ``keys`` is an error: every figure has its column."""
    out = np.full((clients, len(keys)), fill, dtype=np.float64)
    index = {k: i for i, k in enumerate(keys)}
    for client, row in rows.items():
        unknown = sorted(set(row) - set(index))
        if unknown:
            raise KeyError(f"client {client}'s figures {unknown[:5]} have no column")
        out[client] = math.nan
        for key, value in row.items():
            out[client, index[key]] = value
    return out


@dataclass(frozen=True)
class RoundLog:
    """Per-client rows of one round (after the collective: all clients); built whole."""

    round: int
    task: str
    keys: list[str]  # the table's columns, by MLflow key
    table: np.ndarray  # (clients, len(keys))
    seconds: float
    missing: tuple[int, ...] = ()  # clients that did not report (robots that dropped out)
    # The server's own figures: its cost (cost/server_*), its evaluation (server/test/*).
    server: dict[str, float] = field(default_factory=dict)
    # federated.server_eval: the initial model's scores, before round 1 (step 0).
    initial: dict[str, float] = field(default_factory=dict)
    participants: tuple[int, ...] | None = None  # the clients that trained (None: all)
    # what the server refused: client -> "upload: why", "scores: why" (both: "; ")
    refused: dict[int, str] = field(default_factory=dict)
    # simulated faults (fedlgr.core.faults): client -> dropped, late, byzantine (attack)
    faults: dict[int, str] = field(default_factory=dict)
    # who each client is where it is a robot: client -> "robot2 (client 2)"
    names: dict[int, str] = field(default_factory=dict)
    # the headline of the clients' scores (:func:`headline`): the mean, or where the server
    # cannot tell an honest robot's scores from a liar's, the robust strategy's statistic
    statistic: str = "mean"
    # the simulated attackers (federated.faults.byzantine): their scores are kept apart
    byzantine: tuple[int, ...] = ()
    # sample counts the server capped (federated.count_cap): client -> "sample count ..."
    capped: dict[int, str] = field(default_factory=dict)

    def who(self, client: int) -> str:
        """The client as the console and MLflow name it: its robot, or ``client N``."""
        return self.names.get(client, f"client {client}")

    def fault(self, client: int) -> str:
        """What went wrong with the client in this round ("": nothing): results.csv's
        ``fault`` column."""
        parts = [self.faults[client]] if client in self.faults else []
        refused = self.refused.get(client, "")
        if refused:
            parts.append(f"refused {refused}")
        if client in self.capped:
            parts.append(self.capped[client])
        if client in self.missing and "scores: " not in refused:
            parts.append("missing")  # a robot whose scores did not come
        return "; ".join(parts)

    @property
    def fields(self) -> list[Field]:
        return [Field(column(k), k) for k in self.keys]

    @property
    def column_names(self) -> list[str]:
        return [column(k) for k in self.keys]

    def column(self, name: str) -> np.ndarray:
        """One figure of every client: by its MLflow key (``test/pcc``) or its results.csv
        column (``test_pcc``)."""
        keys = self.keys
        index = keys.index(name) if name in keys else self.column_names.index(name)
        return self.table[:, index]

    def key(self, name: str) -> str:
        """The MLflow key of ``name``, a key or a results.csv column."""
        return name if name in self.keys else self.keys[self.column_names.index(name)]

    @property
    def counted(self) -> np.ndarray:
        """Which clients' scores make the headline (a bool per client): not a known attacker,
        nor a client whose upload the server refused - its word is not taken."""
        mask = np.ones(len(self.table), dtype=bool)
        refused = [c for c, why in self.refused.items() if why.startswith("upload: ")]
        out = [*self.byzantine, *refused]
        mask[[c for c in out if isinstance(c, int) and 0 <= c < len(mask)]] = False
        return mask

    def over_clients(self, values: np.ndarray) -> float | None:
        """The headline of one score's ``values`` (one per client): :attr:`statistic` over
        the clients :attr:`counted`; None where none of them has a value."""
        return headline(np.asarray(values)[self.counted], self.statistic)

    def mean(self, name: str) -> float | None:
        """One figure over the clients: a score's headline (:meth:`over_clients`), any other
        figure's mean over every client that has it (a cost, a training loss)."""
        column_ = self.column(name)
        if is_score(self.key(name)):
            return self.over_clients(column_)
        return headline(column_)

    def apart(self, name: str) -> float | None:
        """A score's mean over the simulated attackers (None: none, or none scored)."""
        return headline(self.column(name)[list(self.byzantine)]) if self.byzantine else None

    def spread(self, name: str) -> float | None:
        """The interquartile range of a score over the clients that count (None: none)."""
        values = self.column(name)[self.counted]
        values = values[~np.isnan(values)]
        if not values.size:
            return None
        high, low = np.percentile(values, [75, 25])
        return float(high - low)

    def outliers(self) -> dict[int, str]:
        """The clients that count whose headline score is far from the others' median
        (:data:`OUTLIER_MADS`), client -> "RMSE 0.010 (median 0.674)"; at least 3 are
        needed to tell."""
        out: dict[int, str] = {}
        for score in (s for s in SCORES if s.headline and f"test/{s.name}" in self.keys):
            values = self.column(f"test/{score.name}")
            clients = [c for c in np.flatnonzero(self.counted) if not math.isnan(values[c])]
            if len(clients) < 3:
                continue
            median = float(np.median(values[clients]))
            mad = float(np.median(np.abs(values[clients] - median)))
            far = max(OUTLIER_MADS * 1.4826 * mad, OUTLIER_FLOOR * max(1.0, abs(median)))
            for c in clients:
                if abs(values[c] - median) > far and int(c) not in out:
                    out[int(c)] = f"{score.label} {values[c]:.3f} (median {median:.3f})"
        return out

    def rows(self) -> list[dict[str, object]]:
        out = []
        names = self.column_names
        for client, values in enumerate(self.table):
            row: dict[str, object] = {"round": self.round, "task": self.task, "client": client}
            row.update(
                {n: None if math.isnan(v) else float(v) for n, v in zip(names, values, strict=True)}
            )
            row["fault"] = self.fault(client)
            # the run's privacy so far (client-level DP), on each of the round's rows
            row.update({column(k): v for k, v in self.server.items() if k.startswith("privacy/")})
            out.append(row)
        return out

    def metrics(self) -> dict[str, float]:
        """MLflow metrics of this round: the clients' headline (``test/rmse``: :meth:`mean`)
        and per-client values under the same family (``test/client3/rmse``,
        ``cost/client3/cpu_s``), so that MLflow's charts group a family's headline with its
        clients; the simulated attackers' mean score apart (``byzantine/test/rmse``), each
        headline score's spread (``spread/test/rmse``, the interquartile range) and the
        number of outliers (``round/outliers``)."""
        out: dict[str, float] = {"round/seconds": self.seconds, **self.server}
        if self.missing:
            out["round/missing_clients"] = float(len(self.missing))
        if self.participants is not None:
            out["round/participants"] = float(len(self.participants))
        if self.refused:
            out["faults/refused"] = float(len(self.refused))
        if self.capped:
            out["faults/capped"] = float(len(self.capped))
        outliers = self.outliers()
        if outliers:
            out["round/outliers"] = float(len(outliers))
        headlines = {f"test/{s.name}" for s in SCORES if s.headline}
        for key, values in zip(self.keys, self.table.T, strict=True):
            value = self.over_clients(values) if is_score(key) else headline(values)
            if value is not None:
                out[key] = value
            if is_score(key) and (apart := self.apart(key)) is not None:
                out[f"byzantine/{key}"] = apart
            if key in headlines and (spread := self.spread(key)) is not None:
                out[f"spread/{key}"] = spread
            for client, value in enumerate(values):
                if not math.isnan(value):
                    out[client_key(key, client)] = float(value)
        return out
