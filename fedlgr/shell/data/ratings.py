"""Read and validate ``all_data.csv`` and average the ratings of each scene (docs/data.md);
every problem is collected, named by row (line r + 1) or stamp and column, in one error."""

from __future__ import annotations

import csv
import math
from collections import Counter
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from fedlgr.core.data.columns import (
    ALL_COLUMNS,
    CSV_NAME,
    DESCRIPTOR_COLUMNS,
    LABEL_COLUMNS,
    LIKERT_MAX,
    LIKERT_MIN,
    MODE_COLUMNS,
    STAMP,
)
from fedlgr.core.data.scenes import SceneTable
from fedlgr.errors import DataError, join_problems

_VALUE_COLUMNS = (*MODE_COLUMNS, *DESCRIPTOR_COLUMNS, *LABEL_COLUMNS)

# Descriptors are 0..1 (raw ones stay in the tens): a magnitude over a million is an error or a
# sentinel, and overflows float32 once squared in a variance or a loss.
DESCRIPTOR_LIMIT = 1e6
_INT64 = np.iinfo(np.int64)


def _check_header(path: Path, header: list[str]) -> dict[str, int]:
    names = [h.strip() for h in header]
    problems = [f"missing column {c!r}" for c in ALL_COLUMNS if c not in names]
    problems += [f"unexpected column {c!r}" for c in names if c not in ALL_COLUMNS]
    problems += [f"column {c!r} appears {k} times" for c, k in Counter(names).items() if k > 1]
    if problems:
        raise DataError(join_problems(str(path), problems))
    return {c: names.index(c) for c in ALL_COLUMNS}


def _parse_cell(text: str, column: str, where: str, problems: list[str]) -> float:
    at, raw = f"{where}, column {column!r}", text.strip()
    label = column in LABEL_COLUMNS
    try:
        value = float(text)
    except ValueError:
        if raw == "" and label:
            problems.append(f"{at}: NaN label (empty)")
        else:
            problems.append(f"{at}: non-numeric value {text!r}")
        return math.nan
    if math.isnan(value):
        problems.append(f"{at}: NaN label" if label else f"{at}: NaN value")
    elif math.isinf(value):
        problems.append(f"{at}: infinite value {raw!r}")
    elif label and not LIKERT_MIN <= value <= LIKERT_MAX:
        problems.append(f"{at}: Likert value {raw} outside {LIKERT_MIN}..{LIKERT_MAX}")
    elif column in MODE_COLUMNS and value not in (0.0, 1.0):
        problems.append(f"{at}: mode flag {raw} is not 0 or 1")
    elif column in DESCRIPTOR_COLUMNS and abs(value) > DESCRIPTOR_LIMIT:
        problems.append(
            f"{at}: value {raw} is beyond +-{DESCRIPTOR_LIMIT:g} (descriptors are normalised "
            "to 0..1)"
        )
    return value


def _parse_stamp(text: str, where: str, problems: list[str]) -> int:
    """The stamp as an exact integer: float64 would merge stamps beyond 2**53 into one scene."""
    raw = text.strip()
    try:
        number = Decimal(raw)  # exact; also reads "251.0" and "2.51e2"
        integral = number.is_finite() and number == number.to_integral_value()
    except InvalidOperation:
        integral = False
    if not integral:
        problems.append(f"{where}, column {STAMP!r}: stamp {raw!r} is not an integer")
        return 0
    # adjusted() is the decimal exponent: it bounds the size before int() builds the number
    if number.adjusted() > 19 or not _INT64.min <= int(number) <= _INT64.max:
        problems.append(
            f"{where}, column {STAMP!r}: stamp {raw!r} is outside the 64-bit integer range"
        )
        return 0
    return int(number)


def read_ratings(path: Path | str) -> SceneTable:
    """Read a MANNERS-DB ``all_data.csv`` and average its ratings per stamp; a
    :class:`DataError` names every row/stamp and column at fault."""
    path = Path(path)
    if path.is_dir():
        path = path / CSV_NAME
    if not path.is_file():
        raise DataError(f"{path}: file not found (expected the MANNERS-DB ratings CSV)")
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise DataError(f"{path}: cannot read CSV ({err})") from err
    if not rows:
        raise DataError(f"{path}: file is empty (expected a header with the 38 MANNERS-DB columns)")
    index = _check_header(path, rows[0])
    data = [r for r in rows[1:] if any(cell.strip() for cell in r)]
    if not data:
        raise DataError(f"{path}: no data rows below the header")

    problems: list[str] = []
    stamps = np.zeros(len(data), dtype=np.int64)
    parsed = np.full((len(data), len(_VALUE_COLUMNS)), np.nan)
    for r, row in enumerate(data, start=1):
        where = f"row {r} (line {r + 1})"
        if len(row) != len(rows[0]):
            problems.append(f"{where}: {len(row)} fields, the header has {len(rows[0])}")
            continue
        stamps[r - 1] = _parse_stamp(row[index[STAMP]], where, problems)
        for j, column in enumerate(_VALUE_COLUMNS):
            parsed[r - 1, j] = _parse_cell(row[index[column]], column, where, problems)
        circle, arrow = parsed[r - 1, 0], parsed[r - 1, 1]
        if {circle, arrow} <= {0.0, 1.0} and circle + arrow != 1.0:
            problems.append(
                f"{where}, columns {MODE_COLUMNS[0]!r}/{MODE_COLUMNS[1]!r}: "
                f"exactly one must be 1, got {circle:g}/{arrow:g}"
            )
    if problems:
        raise DataError(join_problems(str(path), problems))
    return _average(path, stamps, parsed)


def _average(path: Path, row_stamps: np.ndarray, parsed: np.ndarray) -> SceneTable:
    """Mean of ``parsed`` (a row per rating) over each stamp's rows, which must agree on the mode
    flags and descriptors: they describe the scene, and only the labels are averaged."""
    stamps, inverse, counts = np.unique(row_stamps, return_inverse=True, return_counts=True)
    scene = [_VALUE_COLUMNS.index(c) for c in (*MODE_COLUMNS, *DESCRIPTOR_COLUMNS)]
    lo = np.full((len(stamps), len(scene)), np.inf)
    hi = np.full((len(stamps), len(scene)), -np.inf)
    np.minimum.at(lo, inverse, parsed[:, scene])
    np.maximum.at(hi, inverse, parsed[:, scene])
    # Equal up to how a CSV writer may round them (real data repeats the same text).
    differ = (hi - lo) > 1e-6 * np.maximum(1.0, np.abs(hi))
    problems = []
    for s in np.flatnonzero(differ.any(axis=1)):
        rows = (np.flatnonzero(inverse == s) + 1).tolist()
        columns = [_VALUE_COLUMNS[scene[j]] for j in np.flatnonzero(differ[s])]
        named = f"column {columns[0]!r}" if len(columns) == 1 else f"columns {columns[0]!r}"
        if len(columns) > 1:
            named += f" and {len(columns) - 1} more"
        problems.append(f"stamp {stamps[s]}, {named}: its rows {rows} disagree")
    if problems:
        raise DataError(
            join_problems(str(path), problems)
            + " (a scene's mode flags and descriptors must be the same in all its rows; "
            "only the 8 ratings are averaged)"
        )
    sums = np.zeros((len(stamps), len(_VALUE_COLUMNS)))
    np.add.at(sums, inverse, parsed)
    means = sums / counts[:, None]
    values = {c: means[:, j] for j, c in enumerate(_VALUE_COLUMNS)}
    return SceneTable(path, stamps, values, counts)
