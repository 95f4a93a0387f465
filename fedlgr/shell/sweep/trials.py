"""What a study holds, read: what is left to run, a grid point handed out twice, every
trial as a row, and the table a sweep ends with."""

from __future__ import annotations

import math
from typing import Any

from fedlgr.shell.console import table
from fedlgr.shell.sweep.space import SweepSpec

# A sampler whose last draws were all points already run has, by all signs, no new one.
DUPLICATES_IN_A_ROW = 50


def one_line(err: BaseException) -> str:
    """``Type: first line of the message``: how a trial's error is recorded and shown."""
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}".rstrip(": ")


def point_key(spec: SweepSpec, params: dict[str, Any]) -> tuple | None:
    """A trial's params as a tuple in the space's order (equal points, equal keys), or None when
    they are not a point of this space."""
    if params.keys() != {p.name for p in spec.params}:
        return None
    return tuple(params[p.name] for p in spec.params)


def retried(trials) -> set[int]:
    """The numbers of the trials of which a copy has been queued."""
    return {n for t in trials for n in t.system_attrs.get("retry_history", [])}


def _split(trials):
    """(running, waiting, finished) trials; finished leaves out skipped duplicates and the
    failed trials that were queued again (their copy stands for them)."""
    again = retried(trials)
    running = [t for t in trials if t.state.name == "RUNNING"]
    waiting = [t for t in trials if t.state.name == "WAITING"]
    finished = [
        t
        for t in trials
        if t.state.is_finished()
        and "duplicate_of" not in t.user_attrs
        and not (t.state.name == "FAIL" and t.number in again)
    ]
    return running, waiting, finished


def counts(study, spec: SweepSpec) -> tuple[int, int, int]:
    """(trials still to start, running, waiting) - what is left of the study. A grid's
    points are never listed (a grid can hold millions): trials are matched by key."""
    trials = study.get_trials(deepcopy=False)
    running, waiting, finished = _split(trials)
    if spec.sampler == "grid":
        values = [set(p.values) for p in spec.params]

        def in_grid(key: tuple | None) -> bool:
            return key is not None and all(v in vs for v, vs in zip(key, values, strict=True))

        covered = {k for t in finished if in_grid(k := point_key(spec, t.params))}
        open_points = math.prod(len(vs) for vs in values) - len(covered)
        # Wait only for running trials that may still cover an open point.
        running = [
            t
            for t in running
            if not t.params or (in_grid(k := point_key(spec, t.params)) and k not in covered)
        ]
        todo = open_points - len({point_key(spec, t.params) for t in running if t.params})
    else:
        todo = max(0, spec.n_trials - len(finished) - len(running) - len(waiting))
        if no_new_point(study, spec) is not None:
            todo = 0
    return todo, len(running), len(waiting)


def no_new_point(study, spec: SweepSpec) -> str | None:
    """Why a TPE study can draw no new point, or None: every point of its finite space has run, or
    its last :data:`DUPLICATES_IN_A_ROW` draws were all old points (else it samples for ever)."""
    trials = study.get_trials(deepcopy=False)
    running, _, finished = _split(trials)
    tried = {point_key(spec, t.params) for t in [*finished, *running] if t.params}
    size = spec.space_size()
    if size is not None and len(tried) >= size:
        return f"its space has {size} distinct point{'s' * (size != 1)} and every one has run"
    streak = 0
    for t in sorted(trials, key=lambda t: t.number, reverse=True):
        if not t.state.is_finished():
            continue
        if "duplicate_of" not in t.user_attrs:
            break
        streak += 1
    if streak < DUPLICATES_IN_A_ROW:
        return None
    space = "a continuous space" if size is None else f"its space has {size} distinct points"
    return f"the sampler's last {streak} draws were all points already run ({space})"


def stopped_early(study, spec: SweepSpec) -> str | None:
    """Why a TPE study ends before its ``trials`` (no new point is left), or None."""
    why = no_new_point(study, spec) if spec.sampler != "grid" else None
    return why if why and ran(study) < spec.n_trials else None


def nothing_left(study, spec: SweepSpec, best: dict[str, Any] | None) -> str:
    """The one line a relaunched study with nothing left to run says."""
    done, why = ran(study), stopped_early(study, spec)
    what = f"{done} of {spec.n_trials} trials ran ({why})" if why else f"all {done} trials are done"
    found = f" (best: trial {best['trial']}, {spec.metric} {best['value']:.4f})" if best else ""
    return f"study {study.study_name!r}: {what}; nothing left to run{found}"


def all_failed(study) -> str | None:
    """When every trial that ran failed: how many, and the first one's error."""
    finished = _split(study.get_trials(deepcopy=False))[2]
    if not finished or any(t.state.name != "FAIL" for t in finished):
        return None
    first = finished[0]
    error = first.user_attrs.get("error", "no error recorded")
    return f"all {len(finished)} trials failed; trial {first.number}: {error}"


def failing(study, spec: SweepSpec, since: int = 0) -> str | None:
    """Why the sweep stops, or None: the last ``failures_in_a_row`` finished trials from ``since``
    on all failed (interrupted ones aside); a trial that fails before drawing its point covers none,
    so the sweep would go on for ever."""
    finished = _split(study.get_trials(deepcopy=False))[2]
    streak = []
    for t in sorted((t for t in finished if t.number >= since), key=lambda t: -t.number):
        if t.state.name != "FAIL":
            break
        if not t.user_attrs.get("interrupted"):
            streak.append(t)
        if len(streak) == spec.failures_in_a_row:
            last = streak[0]
            error = last.user_attrs.get("error", "no error recorded")
            return (
                f"stopped after {len(streak)} trials in a row failed (failures_in_a_row: "
                f"{spec.failures_in_a_row}); the last, trial {last.number}: {error}"
            )
    return None


def ran(study) -> int:
    """How many trials have run (finished, duplicates and re-queued failures left out)."""
    return len(_split(study.get_trials(deepcopy=False))[2])


def duplicate_of(study, number: int, params: dict[str, Any]) -> int | None:
    """An earlier trial that covers the same grid point (running or finished without
    failing), if any: GridSampler can hand a point out twice to parallel workers."""
    for t in study.get_trials(deepcopy=False):
        if t.number >= number or "duplicate_of" in t.user_attrs:
            continue
        if t.state.name in ("RUNNING", "COMPLETE", "PRUNED") and t.params == params:
            return t.number
    return None


def describe_param(p) -> Any:
    if p.values:
        return {"choices": list(p.values)} if p.categorical else list(p.values)
    return {"low": p.low, "high": p.high, "log": p.log, "step": p.step}


def interruption(trial, trials) -> str | None:
    """Why a FAILED trial was cut off rather than failing on its own, or None: Ctrl-C or
    SIGTERM (user attr ``interrupted``, set by its worker), or a worker that died (killed,
    machine lost: no error recorded and a copy queued); with the copy that re-runs it."""
    if trial.state.name != "FAIL" or trial.user_attrs.get("error"):
        return None
    # A copy's history lists the trials it stands for, its own original last.
    copies = (t for t in trials if t.system_attrs.get("retry_history", [])[-1:] == [trial.number])
    copy = next(copies, None)
    reason = trial.user_attrs.get("interrupted")
    if not reason:
        if copy is None:
            return None
        reason = "its worker died (no heartbeat)"
    elif reason is True:  # recorded before the reason was
        reason = "Ctrl-C or SIGTERM"
    if copy is None:
        return f"{reason}; not queued again yet"
    return f"{reason}; retried as trial {copy.number}"


def trial_table(study) -> list[dict[str, Any]]:
    """Every trial: number, state, value, params, error / interruption / duplicate / MLflow run."""
    rows = []
    trials = study.get_trials(deepcopy=False)
    for t in trials:
        row = {
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
        why = interruption(t, trials)
        if why is not None:
            row["interrupted"] = why
        rows.append(row)
    return rows


def summary(study, spec: SweepSpec, best: dict[str, Any] | None) -> str:
    """The table a sweep ends with: a row per trial (skipped duplicates left out), the best
    one marked ``*`` in a column of its own, interrupted trials as ``INTERRUPTED`` with
    why; errors longer than the column below it."""
    rows, errors = [], []
    for row in trial_table(study):
        if "duplicate_of" in row:
            continue
        state, note = row["state"], row.get("error", "")
        if "interrupted" in row:
            state, note = "INTERRUPTED", row["interrupted"]
        if note and len(note) > 60:  # the whole error below the table
            errors.append(f"trial {row['trial']}: {note}")
        rows.append(
            [
                row["trial"],
                "*" if best and row["trial"] == best["trial"] else "",
                state,
                "-" if row["value"] is None else f"{row['value']:.4f}",
                " ".join(f"{k}={v}" for k, v in row["params"].items()),
                note[:60],
            ]
        )
    text = table(["trial", "", "state", spec.metric, "params", "error"], rows)
    if errors:
        text += "\n\n" + "\n".join(errors)
    if best:
        shown = " ".join(f"{k}={v}" for k, v in best["params"].items())
        text += f"\n\nbest (*): trial {best['trial']}, {spec.metric} {best['value']:.4f}: {shown}"
    return text
