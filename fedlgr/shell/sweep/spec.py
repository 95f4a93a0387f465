"""Sweep files (``sweeps/NAME.yaml``, docs/sweeps.md): what a sweep varies, over which base config,
towards which objective; :func:`load_sweep` reads and checks one into a ``SweepSpec``."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from fedlgr.errors import ConfigError, first_line
from fedlgr.shell.checks.paths import not_a_file
from fedlgr.shell.config import SETTING_NAME, SWEEPS_DIR, check_interpolations, yaml_reason
from fedlgr.shell.sweep.checks import check_trial_configs, tracking_experiment
from fedlgr.shell.sweep.space import Param, SweepSpec, resolve_config

DIRECTIONS = ("minimize", "maximize")
SAMPLERS = ("grid", "tpe")
PRUNERS = ("median", "none")
MAX_HEARTBEAT_S = 86400  # a day: longer, and a dead worker's trial waits days to retry
MAX_GRID_POINTS = 1_000_000  # GridSampler lists every point (a tuple each) up front
#: The whole-number settings of a sweep file and their least values (defaults: SweepSpec's).
WHOLE_NUMBERS = {"prune_warmup_rounds": 0, "seed": None, "heartbeat_s": 1, "failures_in_a_row": 1}
#: The settings a sweep file may have at its top level: SweepSpec's, with ``objective`` for its
#: metric and direction and ``space`` for its params.
KNOWN = (
    *(f.name for f in fields(SweepSpec) if f.name not in ("path", "params", "metric", "direction")),
    "objective",
    "space",
)

#: ``fail(key, message)``: the ConfigError naming the sweep file and its setting ``key``.
Fail = Callable[[str, str], ConfigError]


def find_sweep(name: str | Path) -> Path:
    """``sweeps/ewc.yaml``, ``ewc.yaml`` or ``ewc`` -> the sweep file."""
    path = Path(name)
    for candidate in (path, SWEEPS_DIR / path, SWEEPS_DIR / f"{path}.yaml"):
        if candidate.is_file():
            return candidate
    # a dangling link, or a path under a FIFO or a file, is named as what it is
    if not path.exists() and (why := not_a_file(path)):
        raise ConfigError(f"sweep {name}: {why}")
    if path.exists() and not path.is_dir():  # a device or a FIFO is there but is no file
        raise ConfigError(f"sweep {name}: not a regular file (a device, pipe or socket)")
    known = ", ".join(sorted(p.stem for p in SWEEPS_DIR.glob("*.yaml")))
    raise ConfigError(f"sweep {name}: no such file; shipped sweeps: {known}")


def load_sweep(
    path: str | Path,
    overrides: list[str] | tuple[str, ...] = (),
    echo: Callable[[str], None] = print,
) -> SweepSpec:
    """Read and check a sweep file - every parameter, the configs its trials make and the
    objective's metric, before anything trains; ``overrides`` (``key=value``) apply to
    every trial; ``echo`` says so before a long check (a large grid)."""
    path = find_sweep(path)
    raw = read_sweep_file(path)

    def fail(key: str, message: str) -> ConfigError:
        return ConfigError(f"{path}: {key}: {message}")

    _check_top_level(raw, path, fail)
    params = _space(raw, fail)
    sampler = _sampler(raw, params, fail)
    trials = raw.get("trials")  # how many a TPE sweep runs (a grid runs each of its points)
    if sampler == "tpe" and (not isinstance(trials, int) or trials < 1):
        raise fail("trials", "a TPE sweep needs trials: N (N >= 1)")
    objective = _objective(raw, fail)
    # median by default for TPE; none for a grid, which wants every point measured
    pruner = raw.get("pruner", "median" if sampler == "tpe" else "none")
    if pruner not in PRUNERS:
        raise fail("pruner", f"{pruner!r}; choose one of {', '.join(PRUNERS)}")
    base = resolve_config(raw["base"], path) if raw.get("base") else None
    fixed = raw.get("overrides") or []  # the key=value settings every trial gets
    if not isinstance(fixed, list) or not all(isinstance(o, str) and "=" in o for o in fixed):
        raise fail("overrides", "expected a list of key=value strings")
    name = str(raw.get("name") or path.stem)
    spec = SweepSpec(
        name=name,
        path=path.resolve(),
        base=base,
        params=params,
        **objective,
        sampler=sampler,
        trials=trials,
        pruner=pruner,
        overrides=(*fixed, *overrides),
        experiment=str(raw.get("experiment") or f"sweep-{name}"),
        description=str(raw.get("description", "")),
        **{key: _integer(raw, key, least, fail) for key, least in WHOLE_NUMBERS.items()},
    )
    if spec.heartbeat_s > MAX_HEARTBEAT_S:
        raise fail("heartbeat_s", f"{spec.heartbeat_s} is above {MAX_HEARTBEAT_S} (one day)")
    _check_overrides(spec, len(fixed))
    check_trial_configs(spec, echo)
    if any(o.split("=", 1)[0].strip() == "tracking.experiment" for o in spec.overrides):
        # An override names the experiment: it wins over the file's ``experiment``.
        spec = replace(spec, experiment=tracking_experiment(spec))
    return spec


def _check_top_level(raw: dict[str, Any], path: Path, fail: Fail) -> None:
    """Every top-level key is a sweep setting; a text file that is no settings at all is
    refused without echoing its text."""
    unknown = sorted(set(raw) - set(KNOWN))
    if not unknown:
        return
    if not SETTING_NAME.fullmatch(str(unknown[0])):
        raise ConfigError(
            f"{path}: not a sweep file: its top level is not `setting: value` lines "
            f"({', '.join(sorted(KNOWN))})"
        )
    raise fail(unknown[0], f"unknown setting; known: {', '.join(sorted(KNOWN))}")


def _space(raw: dict[str, Any], fail: Fail) -> tuple[Param, ...]:
    """The ``space:`` parameters, each checked as Optuna would take it."""
    space = raw.get("space")
    if not isinstance(space, dict) or not space:
        raise fail("space", "needs at least one parameter (key: [values] or key: {low, high})")
    return tuple(_param(name, value, fail) for name, value in space.items())


def _sampler(raw: dict[str, Any], params: tuple[Param, ...], fail: Fail) -> str:
    """``grid`` when every parameter is a list of values, ``tpe`` otherwise; a grid must fit
    in memory, as GridSampler lists all its points."""
    all_grid = all(p.is_grid for p in params)
    sampler = raw.get("sampler", "grid" if all_grid else "tpe")
    if sampler not in SAMPLERS:
        raise fail("sampler", f"{sampler!r}; choose one of {', '.join(SAMPLERS)}")
    if sampler == "grid" and not all_grid:
        ranges = [p.name for p in params if not p.is_grid]
        raise fail("sampler", f"grid needs a list of values for every parameter, not {ranges}")
    points = math.prod(len(p.values) for p in params) if sampler == "grid" else 0
    if points > MAX_GRID_POINTS:
        raise fail(
            "space",
            f"a {points:,}-point grid; at most {MAX_GRID_POINTS:,} (Optuna's GridSampler "
            f"holds every point in memory, ~{points * (56 + 8 * len(params)) / 1e9:,.0f} GB "
            "here, and each point is a trial): fewer values, or sampler: tpe with trials: N",
        )
    return sampler


def _objective(raw: dict[str, Any], fail: Fail) -> dict[str, str]:
    """The objective's metric and direction."""
    objective = raw.get("objective") or {}
    if not isinstance(objective, dict) or not isinstance(objective.get("metric", ""), str):
        raise fail("objective", "expected {metric: NAME, direction: minimize|maximize}")
    extra = sorted(set(objective) - {"metric", "direction"})
    if extra:
        raise fail(f"objective.{extra[0]}", "unknown setting; known: metric, direction")
    direction = objective.get("direction", "minimize")
    if direction not in DIRECTIONS:
        raise fail("objective.direction", f"{direction!r}; choose minimize or maximize")
    return {"metric": objective.get("metric", SweepSpec.metric), "direction": direction}


def _check_overrides(spec: SweepSpec, in_file: int) -> None:
    """Refuse what a trial would drop without a word: a setting given twice in the file's
    ``overrides:``, or an override of a setting the space varies. The command line's may change the
    file's: that is their use."""
    swept = {p.name for p in spec.params}
    seen: dict[str, str] = {}
    for k, override in enumerate(spec.overrides):
        key = override.split("=", 1)[0].strip()
        where = "its overrides:" if k < in_file else "the command line"
        if key in swept:
            raise ConfigError(
                f"sweep {spec.name}: {override!r} ({where}) sets {key}, which its space: "
                f"varies, each trial its own value; drop it, or take {key} out of space:"
            )
        if k < in_file and key in seen:
            raise ConfigError(
                f"sweep {spec.name}: its overrides: set {key} twice ({seen[key]!r}, "
                f"{override!r}); keep one"
            )
        seen[key] = override


def read_sweep_file(path: Path) -> dict[str, Any]:
    """The settings of a sweep file as a dict, ``${...}`` resolved; a file that is not YAML
    (with the line where YAML says), repeats a key or is not a mapping is one ConfigError
    naming the file."""
    # lazy: omegaconf and yaml, only when a sweep file is read (kept off fedlgr --help)
    import yaml
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        top = yaml.safe_load(path.read_text(encoding="utf-8"))
        if top is not None and not isinstance(top, dict):
            kind = "list" if isinstance(top, list) else type(top).__name__  # not its text
            raise ConfigError(
                f"{path}: a sweep file is a mapping of settings (base, objective, space, ...), "
                f"not a {kind}"
            )
        # OmegaConf's loader also refuses a key given twice, which safe_load lets pass.
        raw = {}
        if top:
            node = OmegaConf.load(path)
            # The config files' rule: ${setting} references and ${oc.env:FEDLGR_*} only.
            check_interpolations(path, node)
            raw = OmegaConf.to_container(node, resolve=True)
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}{_yaml_problem(err)}") from err
    except OmegaConfBaseException as err:  # e.g. ${...} that names nothing
        key = f"{err.full_key}: " if getattr(err, "full_key", None) else ""
        raise ConfigError(f"{path}: {key}{first_line(err)}") from err
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: cannot read the sweep file: {err}") from err
    except RecursionError:  # thousands of nested levels
        raise ConfigError(f"{path}: nested too deeply to be a sweep file") from None
    return raw


def _yaml_problem(err) -> str:
    """``, line L, column C: not valid YAML: PROBLEM (CONTEXT from line ...)``."""
    problem = getattr(err, "problem", None) or str(err).splitlines()[0]
    if "YAML node expansion" in problem:  # OmegaConf's limit on one file's nodes
        return f": {yaml_reason(Exception(problem))}; give a long list as low/high/step"
    mark = getattr(err, "problem_mark", None)
    where = f", line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    context, start = getattr(err, "context", None), getattr(err, "context_mark", None)
    if context and start is not None:
        problem += f" ({context} from line {start.line + 1}, column {start.column + 1})"
    elif context:
        problem += f" ({context})"
    return f"{where}: not valid YAML: {problem}"


def _integer(raw: dict[str, Any], key: str, minimum: int | None, fail: Fail) -> int:
    value = raw.get(key, getattr(SweepSpec, key))
    if isinstance(value, bool) or not isinstance(value, int):
        raise fail(key, f"expected a whole number, not {value!r}")
    if minimum is not None and value < minimum:
        raise fail(key, f"{value} is below {minimum}")
    return value


#: Settings each trial's config gets from the sweep, whatever the space says.
SET_BY_THE_SWEEP = {
    "tracking.uri": "--tracking-uri",
    "tracking.experiment": "the sweep's experiment, sweep-NAME",
    "tracking.run_name": "its method and point",
}


def _param(name: str, value: Any, fail: Fail) -> Param:
    """One ``space`` entry, checked as Optuna would take it (a grid, choices or a range)."""
    key = f"space.{name}"
    if name in SET_BY_THE_SWEEP:  # the sweep sets it for every trial: swept, it does nothing
        raise fail(key, f"set by the sweep for every trial ({SET_BY_THE_SWEEP[name]}), not swept")
    if isinstance(value, list):
        return Param(name, values=_values(value, key, "grid", fail))
    if not isinstance(value, dict):
        raise fail(key, f"expected a list (grid) or {{low, high}} / {{choices}}, not {value!r}")
    if "choices" not in value:
        return _range(name, value, key, fail)
    extra = sorted(set(value) - {"choices"})  # {choices: [...]}: categorical values
    if extra:
        raise fail(key, f"unknown setting(s) {extra} next to choices (a list of values)")
    choices = value["choices"]
    if not isinstance(choices, list):
        raise fail(key, f"choices: expected a list of values, not {choices!r}")
    return Param(name, values=_values(choices, key, "choices", fail), categorical=True)


def _range(name: str, value: dict, key: str, fail: Fail) -> Param:
    """``{low, high, log?, step?}``: a numeric range, as Optuna draws from it."""
    extra = sorted(set(value) - {"low", "high", "log", "step"})
    if extra:
        raise fail(key, f"unknown range setting(s) {extra}; use low, high, log, step")
    if "low" not in value or "high" not in value:
        raise fail(key, "a range needs low and high (or use a list for a grid)")
    low, high, log, step = value["low"], value["high"], value.get("log", False), value.get("step")
    for setting, number in (("low", low), ("high", high)):
        if isinstance(number, bool) or not isinstance(number, int | float):
            raise fail(key, f"{setting} must be a number, not {number!r}")
        if not math.isfinite(number):
            raise fail(key, f"{setting} must be a finite number, not {number}")
    if low >= high:
        raise fail(key, f"low ({low}) must be below high ({high})")
    if not isinstance(log, bool):
        raise fail(key, f"log: expected true or false, not {log!r}")
    if log and low <= 0:
        raise fail(key, "a log range needs low > 0")
    if step is not None:
        _check_step(step, low, high, log, key, fail)
    param = Param(name, low=low, high=high, log=log, step=step)
    try:
        param.distribution()  # anything else Optuna refuses
    except ValueError as err:
        raise fail(key, first_line(err)) from err
    return param


def _check_step(step: Any, low: float, high: float, log: bool, key: str, fail: Fail) -> None:
    number = not isinstance(step, bool) and isinstance(step, int | float)
    if not number or not math.isfinite(step) or step <= 0:
        raise fail(key, f"step must be a number above 0, not {step!r}")
    if log:
        raise fail(key, "step and log: true cannot go together (Optuna draws either)")
    if step > high - low:
        raise fail(key, f"step ({step}) is larger than the range ({low} to {high})")


def _values(values: list[Any], key: str, what: str, fail: Fail) -> tuple[Any, ...]:
    """A grid's or choices' values: numbers, strings, booleans or null, each once."""
    if not values:
        raise fail(key, f"an empty {what}")
    seen: list[Any] = []
    for v in values:
        if not (v is None or isinstance(v, str | int | float | bool)):
            raise fail(key, f"{what} values must be numbers, strings or booleans, not {v!r}")
        if isinstance(v, float) and math.isnan(v):
            raise fail(key, f"{what} values cannot be .nan (it equals no value, not even itself)")
        if any(type(v) is type(u) and v == u for u in seen):
            raise fail(key, f"{v!r} is listed twice")
        seen.append(v)
    return tuple(values)
