"""What a study holds, read: what is left to run, a grid point handed out twice, every
trial as a row, and the table a sweep ends with."""

from __future__ import annotations

from typing import Any

from fedlgr.sweep.spec import SweepSpec


def same_point(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two trials' params are the same grid point."""
    return a.keys() == b.keys() and all(a[k] == b[k] for k in a)


def counts(study, spec: SweepSpec) -> tuple[int, int, int]:
    """(trials still to start, running, waiting) - what is left of the study."""
    from optuna.trial import TrialState

    trials = study.get_trials(deepcopy=False)
    retried = {n for t in trials for n in t.system_attrs.get("retry_history", [])}
    running = [t for t in trials if t.state == TrialState.RUNNING]
    waiting = [t for t in trials if t.state == TrialState.WAITING]
    finished = [
        t
        for t in trials
        if t.state.is_finished()
        and "duplicate_of" not in t.user_attrs
        and not (t.state == TrialState.FAIL and t.number in retried)
    ]
    if spec.sampler == "grid":
        points = spec.grid_points()
        open_points = [p for p in points if not any(same_point(p, t.params) for t in finished)]
        # Wait only for running trials that may still cover an open point.
        running = [
            t for t in running if not t.params or any(same_point(p, t.params) for p in open_points)
        ]
        covered = [t.params for t in running]
        todo = sum(not any(same_point(p, c) for c in covered) for p in open_points)
    else:
        todo = max(0, spec.n_trials - len(finished) - len(running) - len(waiting))
    return todo, len(running), len(waiting)


def duplicate_of(study, number: int, params: dict[str, Any]) -> int | None:
    """An earlier trial that covers the same grid point (running or finished without
    failing), if any: GridSampler can hand a point out twice to parallel workers."""
    from optuna.trial import TrialState

    for t in study.get_trials(deepcopy=False):
        if t.number >= number or "duplicate_of" in t.user_attrs:
            continue
        alive = t.state in (TrialState.RUNNING, TrialState.COMPLETE, TrialState.PRUNED)
        if alive and same_point(t.params, params):
            return t.number
    return None


def describe_param(p) -> Any:
    if p.values:
        return {"choices": list(p.values)} if p.categorical else list(p.values)
    return {"low": p.low, "high": p.high, "log": p.log, "step": p.step}


def trial_table(study) -> list[dict[str, Any]]:
    """Every trial: number, state, value, params, error / duplicate / MLflow run."""
    rows = []
    for t in study.get_trials(deepcopy=False):
        rows.append(
            {
                "trial": t.number,
                "state": t.state.name,
                "value": t.value,
                "params": t.params,
                **{
                    k: t.user_attrs[k]
                    for k in ("error", "duplicate_of", "mlflow_run_id")
                    if k in t.user_attrs
                },
            }
        )
    return rows


def summary(study, spec: SweepSpec, best: dict[str, Any] | None) -> str:
    from fedlgr.console import table

    rows = []
    for row in trial_table(study):
        if "duplicate_of" in row:
            continue
        note = row.get("error", "")
        mark = " *" if best and row["trial"] == best["trial"] else ""
        rows.append(
            [
                f"{row['trial']}{mark}",
                row["state"],
                "-" if row["value"] is None else f"{row['value']:.4f}",
                " ".join(f"{k}={v}" for k, v in row["params"].items()),
                note[:60],
            ]
        )
    text = table(["trial", "state", spec.metric, "params", "error"], rows)
    if best:
        shown = " ".join(f"{k}={v}" for k, v in best["params"].items())
        text += f"\n\nbest (*): trial {best['trial']}, {spec.metric} {best['value']:.4f}: {shown}"
    return text
