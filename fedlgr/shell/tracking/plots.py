"""The run's PNG: every headline score per round (test RMSE, PCC, CCC: a panel each), the
mean over clients and each client."""

from __future__ import annotations

import io
from collections.abc import Sequence

from fedlgr.core.metrics import column, headline_scores


def curves_png(rows: Sequence[dict[str, object]], title: str = "") -> bytes:
    """Every headline score per round from the per-round/per-client result rows, under ``title``."""
    import matplotlib  # lazy: matplotlib (seconds), only when a run's curves are drawn

    matplotlib.use("Agg")  # no display: files only
    import matplotlib.pyplot as plt  # lazy: as matplotlib, once its backend is chosen

    def value(row, metric: str) -> float:  # a diverged round's score is None: a gap
        return float("nan") if row[metric] is None else float(row[metric])

    scores = headline_scores()
    rounds = sorted({int(r["round"]) for r in rows})
    clients = sorted({int(r["client"]) for r in rows})
    fig, axes = plt.subplots(
        1, len(scores), figsize=(4.5 * len(scores), 3.4), squeeze=False, constrained_layout=True
    )
    for ax, score in zip(axes[0], scores, strict=True):
        metric = column(f"test/{score.name}")  # its results.csv column: test_rmse
        for c in clients:
            values = [
                next(value(r, metric) for r in rows if r["round"] == k and r["client"] == c)
                for k in rounds
            ]
            ax.plot(rounds, values, color="0.7", linewidth=0.8)
        means = [
            sum(value(r, metric) for r in rows if r["round"] == k) / len(clients) for k in rounds
        ]
        ax.plot(rounds, means, color="C0", linewidth=2, marker="o", label="mean over clients")
        ax.set_xlabel("round")
        ax.set_ylabel(f"test {score.label}")
        ax.grid(alpha=0.3)
    axes[0][-1].legend(loc="lower right")
    if title:
        fig.suptitle(title)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return buffer.getvalue()
