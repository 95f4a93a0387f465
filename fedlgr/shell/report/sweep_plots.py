"""Optuna's own views of a sweep's study, as PNGs (``optuna.visualization.matplotlib``).

Optuna marks these functions experimental; the warning is silenced around them only.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from fedlgr.shell.report.plots import pyplot

# fANOVA fits a random forest to the completed trials: on fewer points it ranks noise.
MIN_TRIALS_FOR_IMPORTANCE = 6


def write_study_plots(study: Any, metric: str, params: list[str], out: Path) -> tuple[list, list]:
    """Draw the plots that fit the study into ``out``; returns the files written and the
    lines that say which were left out and why."""
    import optuna  # lazy: optuna and matplotlib (seconds), only for a sweep's report
    from optuna.visualization import matplotlib as views  # lazy: as optuna

    done = study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
    if not done:
        return [], ["Optuna's plots: not drawn, no trial completed."]
    varied = [p for p in params if len({repr(t.params.get(p)) for t in done}) > 1]
    plots = {
        "optuna_history.png": lambda: views.plot_optimization_history(study, target_name=metric),
        "optuna_slice.png": lambda: views.plot_slice(study, params=params, target_name=metric),
    }
    notes = []
    if len(varied) >= 2 and len(done) >= MIN_TRIALS_FOR_IMPORTANCE:
        plots["optuna_importances.png"] = lambda: views.plot_param_importances(
            study, params=varied, target_name=metric
        )
    else:
        notes.append(
            f"Parameter importances: not drawn; they need 2 or more swept settings that vary "
            f"and {MIN_TRIALS_FOR_IMPORTANCE} completed trials (this study: {len(varied)} "
            f"varying, {len(done)} completed)."
        )
    if len(varied) >= 2:
        plots["optuna_contour.png"] = lambda: views.plot_contour(
            study, params=varied, target_name=metric
        )
    else:
        notes.append("Contour plot: not drawn; it needs 2 or more swept settings that vary.")
    plt = pyplot()
    written = []
    for name, draw in plots.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            drawn = draw()
        figure = drawn.figure if hasattr(drawn, "figure") else drawn.flat[0].figure
        if name == "optuna_slice.png":  # long values (1000000) side by side overlap
            for ax in figure.axes[: len(params)]:
                ax.tick_params(axis="x", labelrotation=30)
        figure.savefig(out / name, dpi=110, bbox_inches="tight")
        plt.close(figure)
        written.append(name)
    return written, notes
