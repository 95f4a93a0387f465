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

from fedlgr.core.metrics import client_key, column


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

    def mean(self, name: str) -> float | None:
        column_ = self.column(name)
        return None if np.isnan(column_).all() else float(np.nanmean(column_))

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
        """MLflow metrics of this round: means over clients (``test/rmse``) and per-client
        values under the same family (``test/client3/rmse``, ``cost/client3/cpu_s``), so
        that MLflow's charts group a family's mean with its clients."""
        out: dict[str, float] = {"round/seconds": self.seconds, **self.server}
        if self.missing:
            out["round/missing_clients"] = float(len(self.missing))
        if self.participants is not None:
            out["round/participants"] = float(len(self.participants))
        if self.refused:
            out["faults/refused"] = float(len(self.refused))
        for key, values in zip(self.keys, self.table.T, strict=True):
            if not np.isnan(values).all():
                out[key] = float(np.nanmean(values))
            for client, value in enumerate(values):
                if not math.isnan(value):
                    out[client_key(key, client)] = float(value)
        return out
