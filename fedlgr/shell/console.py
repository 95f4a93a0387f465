"""Console output: plain fixed-width tables, durations, and progress for long work (a bar
on a terminal, log lines elsewhere)."""

from __future__ import annotations

import contextlib
import sys
import threading
import time
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


def duration(seconds: float) -> str:
    """``42 s``, ``4 min``, ``1 h 20 min``: a span of time as a person reads it."""
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    return f"{minutes} min" if minutes < 60 else f"{minutes // 60} h {minutes % 60:02d} min"


class Progress(contextlib.AbstractContextManager):
    """``progress(done, total)`` callback for long work, used as a context manager: a tqdm bar on a
    terminal, else a line on stderr at each tenth done (at most every ``every_s / 3`` s, at least
    every ``every_s`` s) so that logs show progress. Safe to call from several threads."""

    every_s = 30.0

    def __init__(self, desc: str, unit: str = "it", enabled: bool = True):
        self.desc, self.unit, self.bar = desc, unit, None
        self.enabled = enabled
        self.terminal = sys.stderr.isatty()
        self._lock = threading.Lock()
        self._start = self._said = time.monotonic()
        self._tenths = 0

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        with self._lock:
            if not self.terminal:
                self._log(done, total)
                return
            if self.bar is None:
                from tqdm.auto import tqdm  # lazy: tqdm, only on a terminal

                self.bar = tqdm(
                    total=total, desc=self.desc, unit=self.unit, leave=False, dynamic_ncols=True
                )
            self.bar.update(done - self.bar.n)

    def _log(self, done: int, total: int) -> None:
        now = time.monotonic()
        tenths = 10 * done // total if total else 0
        quiet = now - self._said
        if not ((tenths > self._tenths and quiet >= self.every_s / 3) or quiet >= self.every_s):
            return
        self._tenths, self._said = tenths, now
        spent = now - self._start
        left = f", about {duration(spent * (total - done) / done)} left" if 0 < done < total else ""
        percent = f" ({100 * done // total}%)" if total else ""
        print(
            f"{self.desc}: {done}/{total} {self.unit}{percent} after {duration(spent)}{left}",
            file=sys.stderr,
            flush=True,
        )

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()
