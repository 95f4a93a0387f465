"""The view of an experiment's runs that the printed MLflow link opens: the headline figures
first (docs/tracking.md).

MLflow's runs page can be shared: its "Share" button stores the page's state (columns,
sorting, charts, expanded parent runs) as the experiment tag
``mlflow.sharedViewState.<key>``, and ``?viewStateShareKey=<key>`` in the page's address
loads it. fedlgr writes such a view, :data:`VIEW`, to every experiment it logs to:

- the runs table shows ``test/rmse``, ``test/pcc``, ``test/ccc`` and the costs per client
  per round (``mean/cost/cpu_s``, ``mean/cost/bytes_up``) as columns, with the method and
  each sweep's swept settings, sorted by ``test/rmse``; a sweep's trials are shown (their
  parent run expanded);
- the chart view opens on a "headline" section: ``test/rmse`` and ``test/pcc`` of each
  run side by side and a parallel-coordinates plot of the method and swept settings
  against both.

The state is the MLflow UI's own format (MLflow 3.17: ``selectedColumns`` as
``metrics.`key``` / ``params.`key```, chart cards by type); a UI that no longer reads a
field ignores it, and "Exit shared view" gives MLflow's default page.
"""

from __future__ import annotations

import json
from collections.abc import Iterable

from fedlgr.core.metrics import HEADLINE

VIEW = "fedlgr"
TAG = f"mlflow.sharedViewState.{VIEW}"
SECTION = "fedlgr-headline"
# the runs table's metric columns: every score but the loss (the square of the RMSE), then
# the costs; the table sorts them by name and shows about six in a 1400-pixel window
COLUMNS = (*(m for m in HEADLINE if m != "test/loss"), "mean/cost/cpu_s", "mean/cost/bytes_up")
MAX_PARAMS = 6  # in the parallel-coordinates plot, the runs table's columns too
MAX_EXPANDED = 40  # the newest sweeps' parent runs (an experiment tag holds 5000 characters)


def _card(uuid: str, kind: str, **fields) -> dict:
    base = {"uuid": uuid, "type": kind, "metricSectionId": SECTION, "runsCountToCompare": 10}
    return {**base, "deleted": False, "isGenerated": False, **fields}


def view_state(params: Iterable[str], expanded: Iterable[str]) -> dict:
    """The shared state: ``params`` as columns and plot axes, the runs ``expanded`` (sweep
    parent runs) open."""
    params = list(dict.fromkeys(params))[:MAX_PARAMS]
    charts = [
        _card("fedlgr-rmse", "BAR", metricKey="test/rmse", displayName="test/rmse"),
        _card("fedlgr-pcc", "BAR", metricKey="test/pcc", displayName="test/pcc"),
        _card(
            "fedlgr-parallel",
            "PARALLEL",
            selectedParams=params,
            selectedMetrics=["test/rmse", "test/pcc"],
            showAllRuns=False,
        ),
    ]
    section = {"uuid": SECTION, "name": "headline", "display": True, "isReordered": True}
    return {
        "selectedColumns": [f"metrics.`{m}`" for m in COLUMNS] + [f"params.`{p}`" for p in params],
        "orderByKey": "metrics.`test/rmse`",
        "orderByAsc": True,
        "runsExpanded": {run_id: True for run_id in expanded},
        "compareRunCharts": charts,
        "compareRunSections": [{**section, "deleted": False, "isGenerated": False}],
        "isAccordionReordered": True,
    }


def share_view(client, experiment_id: str, params: Iterable[str] = (), parent: str = "") -> None:
    """Write (or widen) the experiment's view: ``method`` and ``params`` as columns and
    plot axes, ``parent`` (a sweep's parent run) expanded; the tag is written only when the
    view changes. A view that cannot be read (edited by hand) is replaced."""
    experiment = client.get_experiment(experiment_id)
    try:
        old = json.loads(experiment.tags.get(TAG, "{}"))
        charts = old.get("compareRunCharts", ())
        old_params = [c["selectedParams"] for c in charts if "selectedParams" in c]
        old_expanded = list(old.get("runsExpanded", {}))
    except (ValueError, TypeError, AttributeError):  # written by hand or by another version
        old_params, old_expanded = [], []
    wanted = ["method", *(old_params[0] if old_params else []), *params]
    expanded = [*old_expanded, *([parent] if parent else [])][-MAX_EXPANDED:]
    state = view_state(wanted, expanded)
    text = json.dumps(state)
    if experiment.tags.get(TAG) != text:
        client.set_experiment_tag(experiment_id, TAG, text)
