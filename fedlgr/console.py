"""Console output: plain fixed-width tables and progress bars for long work."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Sequence


def _cell(value: object) -> str:
    return f"{value:.3f}" if isinstance(value, float) else str(value)


def _numeric(text: str) -> bool:
    try:
        float(text.rstrip("%s"))
    except ValueError:
        return False
    return True


def table(headers: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """A fixed-width text table; numbers right-aligned, floats with 3 decimals."""
    body = [[_cell(v) for v in row] for row in rows]
    widths = [max([len(h)] + [len(r[j]) for r in body]) for j, h in enumerate(headers)]

    def line(values: Sequence[str]) -> str:
        cells = (
            v.rjust(w) if _numeric(v) else v.ljust(w) for v, w in zip(values, widths, strict=True)
        )
        return "  ".join(cells).rstrip()

    return "\n".join([line(headers), "  ".join("-" * w for w in widths), *map(line, body)])


class Progress:
    """``progress(done, total)`` callback drawing a tqdm bar on stderr when it is a terminal
    (silent otherwise, so logs stay clean). Use as a context manager."""

    def __init__(self, desc: str, unit: str = "it", enabled: bool = True):
        self.desc, self.unit, self.bar = desc, unit, None
        self.enabled = enabled and sys.stderr.isatty()

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        if self.bar is None:
            from tqdm.auto import tqdm

            self.bar = tqdm(
                total=total, desc=self.desc, unit=self.unit, leave=False, dynamic_ncols=True
            )
        self.bar.update(done - self.bar.n)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()
