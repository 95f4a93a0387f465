"""The figures a report draws, read back: what each panel's axis says."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from fedlgr.shell.report.plots import pyplot


@contextmanager
def drawn_figures() -> Iterator[dict[str, list[str]]]:
    """``{figure title: [each panel's y label]}`` of every figure drawn inside the block,
    read as the report closes it (after saving it)."""
    plt = pyplot()
    close, drawn = plt.close, {}

    def read_and_close(fig) -> None:
        drawn[fig.get_suptitle()] = [ax.get_ylabel() for ax in fig.axes]
        close(fig)

    plt.close = read_and_close
    try:
        yield drawn
    finally:
        plt.close = close
