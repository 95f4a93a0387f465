"""Loading a config: the defaults, the files it ``includes``, the file and the overrides merged by
OmegaConf, then built; each error is one line naming the setting and its layer."""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException
from omegaconf.tupleconfig import TupleConfig

from fedlgr.core.declare import section_of, type_problem
from fedlgr.core.methods import CONTINUAL, FCL_METHODS, METHODS, SCOPES, STRATEGIES, method_name
from fedlgr.core.settings import (
    DEFAULT_TASKS,
    ContinualConfig,
    ExperimentConfig,
    FederatedConfig,
)
from fedlgr.errors import ConfigError, first_line
from fedlgr.shell.checks.experiment import check_machine
from fedlgr.shell.config.export import known_settings, to_plain
from fedlgr.shell.config.files import read_layers
from fedlgr.shell.config.written import check_interpolations, lookup, plain, strings


def load_config(
    path: Path | str | None = None, overrides: list[str] | tuple[str, ...] = ()
) -> ExperimentConfig:
    """Merge the defaults, ``path`` (with its includes) and ``overrides`` (``key=value``).
    ``${...}`` is checked in every layer before anything resolves."""
    layers = read_layers(Path(path)) if path is not None else []
    bad = [o for o in overrides if "=" not in o or o.startswith("=")]
    if bad:
        raise ConfigError(f"override {bad[0]!r}: expected key=value (e.g. federated.rounds=5)")
    layers = [*layers, ("command line", _dotlist(overrides))]
    interpolated: dict[str, tuple[Any, str]] = {}
    for source, node in layers:
        interpolated.update(check_interpolations(source, node))
    return _build(layers, interpolated)


def config_from_data(data: Any, source: str) -> ExperimentConfig:
    """A config received as data (a robot's copy of the server's resolved config): settings only,
    checked by :func:`check_sent_settings`."""
    check_sent_settings(data, source)
    try:
        node = OmegaConf.create(data)
    except OmegaConfBaseException as err:
        raise ConfigError(f"{source}: {omegaconf_message(err)}") from None
    return _build([(source, node)], {})


def check_sent_settings(data: Any, source: str) -> None:
    """Refuse what would make plain settings read or resolve anything: ``includes`` and
    any ``${`` (in a key or a value). The messages name the setting, never a value."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of settings at the top level")
    if "includes" in data:
        raise ConfigError(f"{source}: includes: refused (a config sent as data reads no files)")
    for key, value in strings(data, keys=True):
        if "${" in value:
            raise ConfigError(
                f"{source}: {key}: holds ${{...}}, which a config sent as data may not "
                "(it is resolved where it was written)"
            )


def _dotlist(overrides) -> Any:
    """The command-line layer; an override whose value YAML cannot read is one line."""
    # RecursionError: a value nested thousands of levels deep ([[[[...]]]])
    unreadable = (yaml.YAMLError, OmegaConfBaseException, ValueError, RecursionError)
    # before OmegaConf reads them: of a setting set whole and by parts, it drops one silently
    if clash := _clashing(overrides):
        raise ConfigError(f"command line: {clash}")
    try:
        return OmegaConf.from_dotlist(list(overrides))
    except unreadable as err:
        for override in overrides:  # name the culprit
            try:
                OmegaConf.from_dotlist([override])
            except unreadable as one:
                shown = override if len(override) <= 120 else f"{override[:100]}..."
                raise ConfigError(f"command line: {shown!r}: {first_line(one)}") from None
        raise ConfigError(f"command line: {first_line(err)}") from None


def _clashing(overrides) -> str | None:
    """Two overrides that set one setting both whole and by its parts (``data.path=D`` and
    ``data=[1,2]``), both named: OmegaConf refuses them naming neither, or drops one."""
    keys = [override.partition("=")[0] for override in overrides]
    for i, key in enumerate(keys):
        for earlier, other in zip(overrides[:i], keys[:i], strict=True):
            if other.startswith(f"{key}.") or key.startswith(f"{other}."):
                return (
                    f"{earlier!r} and {overrides[i]!r} set {min(key, other, key=len)} both "
                    "whole and by its parts; give one of them"
                )
    return None


# --------------------------------------------------------------------------- building


def _build(layers: list, interpolated: dict[str, tuple[Any, str]]) -> ExperimentConfig:
    _require_mandatory(layers)
    merged = _merge(layers, with_defaults=bool(interpolated))
    _resolve(merged, interpolated)
    config = _to_object(merged, layers, interpolated)
    check_machine(config)
    return config


def _resolve(merged: Any, interpolated: dict[str, tuple[Any, str]]) -> None:
    """Resolve each ``${...}`` once, so that a reference to nothing, a loop, an unset
    variable or a value of the wrong type is one line naming the setting and its layer."""
    for key, (source, value) in interpolated.items():
        try:
            OmegaConf.select(merged, key)
        except OmegaConfBaseException as err:
            raise ConfigError(f"{source}: {key}={value!r}: {first_line(err)}") from None


def _merge(layers: list, with_defaults: bool) -> Any:
    """``layers`` merged in order, a ``method`` name expanded where given; a layer that does not fit
    is one line naming it and the setting. The defaults are merged first only where a ``${...}`` may
    name one: as an OmegaConf node they are costly to make and merge."""
    merged = OmegaConf.create(to_plain(ExperimentConfig()) if with_defaults else {})
    for source, node in layers:
        _check_types(source, plain(node))
        try:
            if "method" in node and node["method"] is not None:
                node = _expand_method(node, merged)
            merged = OmegaConf.merge(merged, node)
        except OmegaConfBaseException as err:
            raise ConfigError(f"{source}: {omegaconf_message(err)}") from err
        except ConfigError as err:
            raise ConfigError(f"{source}: {err}") from err
        except TypeError as err:  # "Cannot merge incompatible container types" (a traceback)
            written = plain(node)
            raise ConfigError(f"{source}: {container_mismatch(merged, written) or err}") from err
    return merged


def _check_types(source: str, values: Any, cls: type = ExperimentConfig, at: str = "") -> None:
    """A layer's values of the wrong type, refused naming the layer: a section given one value, a
    word where a number goes. Bounds and choices are checked once the layers are merged, where a
    later layer may have set another."""
    if not isinstance(values, dict):
        return
    fields = cls.__pydantic_fields__
    for key, value in values.items():
        name = f"{at}{key}"
        if not isinstance(key, str):
            raise ConfigError(f"{source}: {name}: unknown setting (--print-config lists them)")
        if key not in fields or value == "???" or (isinstance(value, str) and "${" in value):
            continue  # an unknown name is named once the layers are merged
        section = section_of(fields[key].annotation)
        if section is None:
            if problem := type_problem(cls, key, value):
                raise ConfigError(f"{source}: {problem}")
        elif isinstance(value, dict):
            _check_types(source, value, section, f"{name}.")
        else:
            first = next(iter(section.__pydantic_fields__))
            raise ConfigError(
                f"{source}: {name}={value}: a section of settings, not one value; set its "
                f"parts (e.g. {name}.{first}=...)"
            )


def _named(values: dict) -> dict:
    """``method`` is input shorthand: afterwards it names what the settings say (those
    not written: their defaults)."""
    fed, cont = values.get("federated", {}), values.get("continual", {})
    if not (isinstance(fed, dict) and isinstance(cont, dict)):
        return values  # a section given one value: refused as the settings are built
    strategy = fed.get("strategy", _default(FederatedConfig, "strategy"))
    scope = fed.get("scope", _default(FederatedConfig, "scope"))
    method = cont.get("method", _default(ContinualConfig, "method"))
    tasks = cont.get("tasks", ())
    known = isinstance(strategy, str) and isinstance(scope, str) and isinstance(method, str)
    if known and strategy in STRATEGIES and scope in SCOPES and method in CONTINUAL:
        values["method"] = method_name(strategy, scope, method if tasks else None)
    return values


def _default(cls: type, name: str) -> Any:
    return cls.__pydantic_fields__[name].default


def _to_object(merged: Any, layers: list, interpolated: dict) -> ExperimentConfig:
    """The settings, validated as they are built; a value of the wrong shape is said with the layer
    that wrote it (the earliest first), one from ``${...}`` with what was written."""
    values = _named(OmegaConf.to_container(merged, resolve=True))
    try:
        return ExperimentConfig(**values)
    except ConfigError as err:
        refused = getattr(err, "refusals", ())
        shapes = [
            r for r in refused if r.shape or _interpolated_at(r.setting, interpolated) is not None
        ]
        if not shapes:
            raise
        raise ConfigError(_said_with_layer(shapes, layers, interpolated)) from None


def _interpolated_at(key: str, interpolated: dict) -> str | None:
    """The setting whose ``${...}`` gave ``key`` its value (it, or a section holding it)."""
    return next((k for k in interpolated if key == k or key.startswith(f"{k}.")), None)


def _said_with_layer(shapes: list, layers: list, interpolated: dict) -> str:
    written = [(source, plain(node)) for source, node in layers]
    found = []
    for refused in shapes:
        key = refused.setting
        through = _interpolated_at(key, interpolated)
        if through is not None:  # said with what was written: ${...}
            source, value = interpolated[through]
            found.append((-1, 0, f"{source}: {through}={value!r}: {refused.reason}"))
            continue
        writers = [
            (i, at, source, values)
            for i, (source, values) in enumerate(written)
            for at, name in enumerate(_names(values))
            if name == key or name.startswith(f"{key}.") or key.startswith(f"{name}.")
        ]
        if not writers:
            found.append((len(written), 0, refused.problem))
            continue
        last = max(w[0] for w in writers)
        i, at, source, values = min(w for w in writers if w[0] == last)
        problem = refused.problem
        if problem.endswith(": unknown setting"):
            problem = unknown_setting(key, values)
        found.append((i, at, f"{source}: {problem}"))
    return min(found, key=lambda f: (f[0], f[1]))[2]


def _names(values: Any, prefix: str = "") -> list[str]:
    if not isinstance(values, dict) or not values:
        return [prefix[:-1]] if prefix else []
    return [n for k, v in values.items() for n in _names(v, f"{prefix}{k}.")]


def _require_mandatory(layers: list) -> None:
    """A ``???`` value (e.g. data.path in conf/data/manners.yaml) must be set by a later layer:
    OmegaConf's merge skips ``???``, which would let an earlier default stand in silently."""
    written = [(source, plain(node)) for source, node in layers]  # nothing resolved
    for i, (source, values) in enumerate(written):
        for key in _missing_keys(values):
            later = (lookup(v, key) for _, v in written[i + 1 :])
            if not any(v is not None and v != "???" for v in later):
                raise ConfigError(
                    f"{key}: no value (required by {source}); set it, "
                    f"e.g. {key}=/path/to/manners-db"
                )


def _missing_keys(values: dict, prefix: str = "") -> list[str]:
    """Dotted keys whose value is the mandatory marker ``???`` in this layer's values."""
    keys = []
    for key, value in values.items():
        if value == "???":
            keys.append(f"{prefix}{key}")
        elif isinstance(value, dict):
            keys += _missing_keys(value, f"{prefix}{key}.")
    return keys


def _expand_method(node: Any, merged: Any) -> Any:
    """``method=NAME`` -> strategy and scope; a Table II name sets the CL method too, and,
    if no task schedule is set yet, the schedule of every task in ``data.tasks``; an FL
    name clears the schedule and the CL method."""
    name = str(node["method"])
    if name in METHODS:
        strategy, scope, _ = METHODS[name]
        fl = {"strategy": strategy, "scope": scope}
        return OmegaConf.merge(
            {"federated": fl, "continual": {"tasks": [], "method": "none"}}, node
        )
    if name not in FCL_METHODS:
        known = ", ".join([*METHODS, *FCL_METHODS])
        raise ConfigError(f"method={name}: unknown; known methods: {known}")
    strategy, scope, continual = FCL_METHODS[name]
    update: dict = {
        "federated": {"strategy": strategy, "scope": scope},
        "continual": {"method": continual},
    }
    here = OmegaConf.select(node, "continual.tasks", default=None)
    if not here and not OmegaConf.select(merged, "continual.tasks", default=None):
        tasks = OmegaConf.select(node, "data.tasks", default=None) or OmegaConf.select(
            merged, "data.tasks", default=None
        )
        names = [t["name"] for t in tasks] if tasks else [t.name for t in DEFAULT_TASKS]
        update["continual"]["tasks"] = names
    # Settings given next to the name (in the same file or command line) win over it.
    return OmegaConf.merge(update, node)


# --------------------------------------------------------------------------- messages


def omegaconf_message(err: Exception) -> str:
    key = getattr(err, "full_key", None)
    first = first_line(err)
    return f"{key}: {first}" if key else first


def container_mismatch(merged: Any, written: dict, prefix: str = "") -> str | None:
    """The setting given a mapping where a list goes, or a list where a section goes: what
    OmegaConf's merge refuses with a bare ``TypeError``."""
    for key, value in written.items():
        name = f"{prefix}{key}"
        target = OmegaConf.select(merged, name, default=None, throw_on_missing=False)
        if isinstance(value, dict) and isinstance(target, ListConfig | TupleConfig):
            return f"{name}: a list goes here, not a mapping ({_short(value)})"
        if isinstance(value, list) and isinstance(target, DictConfig):
            return f"{name}: a section of settings goes here, not a list ({_short(value)})"
        if isinstance(value, dict) and isinstance(target, DictConfig):
            found = container_mismatch(merged, value, f"{name}.")
            if found:
                return found
    return None


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def unknown_setting(key: str, written: dict) -> str:
    """``KEY: unknown setting; did you mean NAME?``, matched on the whole dotted name
    (``train.learning_rate`` finds ``train.lr_root``); a section written under ``key`` is matched by
    the one setting it holds."""
    dotted = _dotted_key(key, written)
    if dotted is not None:  # `tracking.run_name: x` in a file
        section, _, rest = dotted.partition(".")
        nest = (
            f"a dotted name is read on the command line only; in a file, nest it: "
            f"`{section}:` and below it, indented, `{rest}: ...`"
        )
        if key in known_settings():
            return f"{key}: {nest}"
        return f"{unknown_setting(key, {})} ({nest})"
    below = lookup(written, key)
    if isinstance(below, dict) and len(below) == 1:
        inner, value = next(iter(below.items()))
        if not isinstance(value, dict):
            key = f"{key}.{inner}"
    close = _closest(key, known_settings())
    hint = f"; did you mean {' or '.join(close)}?" if close else " (--print-config lists them)"
    return f"{key}: unknown setting{hint}"


def _closest(key: str, known: list[str]) -> list[str]:
    """The one or two known names closest to ``key`` (a far second is left out)."""
    close = difflib.get_close_matches(key, known, n=2, cutoff=0.6)
    ratios = [difflib.SequenceMatcher(a=name, b=key).ratio() for name in close]
    return [n for n, r in zip(close, ratios, strict=True) if r >= ratios[0] - 0.05]


def _dotted_key(key: str, written: Any) -> str | None:
    """The key holding a dot, as written in a file's values, on the way to dotted ``key``
    (``tracking.run_name`` for ``{"tracking.run_name": ...}``); None where there is none."""
    parts = key.split(".")
    for i in range(len(parts)):
        if not isinstance(written, dict):
            return None
        for j in range(len(parts), i + 1, -1):  # the longest such key first
            if ".".join(parts[i:j]) in written:
                return ".".join(parts[i:j])
        written = written.get(parts[i])
    return None
