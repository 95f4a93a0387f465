"""Rating CSV files written and read row by row, and dataset folders made of them."""

from __future__ import annotations

import csv
from pathlib import Path

from PIL import Image

from fedlgr.core.data.columns import ALL_COLUMNS

HEADER = list(ALL_COLUMNS)


def read_rows(csv_path: Path) -> list[list[str]]:
    with csv_path.open(newline="") as f:
        return list(csv.reader(f))


def write_rows(csv_path: Path, rows: list[list[str]]) -> Path:
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    with csv_path.open("w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)
    return csv_path


def rating_row(stamp: int, circle: bool, labels: list[float], descriptor: float = 0.5) -> list[str]:
    """One CSV row: the given stamp, mode and 8 labels, every descriptor = ``descriptor``."""
    flags = ["1", "0"] if circle else ["0", "1"]
    return [str(stamp), *flags, *[str(descriptor)] * 27, *(f"{v:g}" for v in labels)]


def write_dataset(
    folder: Path, rows: list[list[str]], sizes: dict[int, tuple[int, int]] | None = None
) -> Path:
    """A dataset folder: all_data.csv holding ``rows`` under the header, and a plain PNG of
    the given (width, height) for each stamp in ``sizes``."""
    write_rows(folder / "all_data.csv", [HEADER, *rows])
    for stamp, size in (sizes or {}).items():
        (folder / "images").mkdir(parents=True, exist_ok=True)
        Image.new("RGB", size, (90, 120, 200)).save(folder / "images" / f"{stamp}.png")
    return folder
