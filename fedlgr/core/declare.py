"""How a setting is declared: a field of a frozen pydantic dataclass with its type, its
default, its bounds and a one-line doc (:func:`setting`); and pydantic's refusals said in
the config's words, one line naming the full setting (``federated.prox.mu=-1: must be >=
0``). Pydantic types and bounds the values; the rules a bound cannot say (one setting
against another) are each section's ``__post_init__``, which raises :class:`ConfigError`.

As OmegaConf read them before: a count takes an integer or its digits (``5``, ``"5"``:
``${oc.env:FEDLGR_X,5}`` gives a string), never ``10.0`` or ``true``; a number takes a
number or its text (YAML reads ``1e-3`` as text), never ``true``, and is finite; a switch
takes ``true``/``false`` (or their words: ``yes``, ``on``, 1, 0), never ``1.0``."""

from __future__ import annotations

import dataclasses
import functools
import typing
from typing import Annotated, Any

from pydantic import (
    BeforeValidator,
    ConfigDict,
    Field,
    PydanticUserError,
    Strict,
    TypeAdapter,
    ValidationError,
)
from pydantic.dataclasses import dataclass as pydantic_dataclass
from pydantic_core import PydanticCustomError

from fedlgr.errors import ConfigError


def _count(value: Any) -> Any:
    """An integer's digits as the integer (``"5"``); anything else for the strict check."""
    if isinstance(value, str) and value.strip().lstrip("+-").isdigit():
        return int(value)
    return value


def _number(value: Any) -> Any:
    """A number, not a switch; an integer too large for a float is not finite."""
    if isinstance(value, bool):
        raise PydanticCustomError("float_type", "not a number")
    if isinstance(value, int) and abs(value) > 1e308:
        raise PydanticCustomError("finite_number", "not finite")
    return value


def _switch(value: Any) -> Any:
    """A switch, not a measure: ``1.0`` is refused (``1`` and ``yes`` are read)."""
    if isinstance(value, float):
        raise PydanticCustomError("bool_type", "not a switch")
    return value


Int = Annotated[int, Strict(), BeforeValidator(_count)]  # 10.0 refused, not rounded
Float = Annotated[float, BeforeValidator(_number)]
Bool = Annotated[bool, BeforeValidator(_switch)]
CONFIG = ConfigDict(extra="forbid", allow_inf_nan=False, coerce_numbers_to_str=True)
MAX_EPOCHS = 100_000  # no config (a robot's included) asks for a run that never ends
EPOCHS_BOUND = "at most {bound} epochs (a fixed bound; the paper's longest is the VAE's 300)"


def setting(default: Any = dataclasses.MISSING, doc: str = "", **rule: Any) -> Any:
    """A settings field: its default (``factory`` for a section), its one-line ``doc`` and
    pydantic's bounds (``ge``, ``gt``, ``le``, ``lt``). ``why`` is said after a broken
    bound, ``said`` replaces the whole complaint and ``over`` the one for a value over
    the upper bound (``{bound}`` is the bound)."""
    said = {k: rule.pop(k) for k in ("why", "said", "over") if k in rule}
    factory = rule.pop("factory", dataclasses.MISSING)
    extra = {"said": said} if said else None
    if factory is not dataclasses.MISSING:
        return Field(default_factory=factory, description=doc, json_schema_extra=extra)
    return Field(default, description=doc, json_schema_extra=extra, **rule)


def epoch_count(default: int | None, doc: str, least: int = 1) -> Any:
    """A count of epochs: at most MAX_EPOCHS, so that no config (a robot's included, sent
    by its server) asks for a run that never ends."""
    return setting(default, doc, ge=least, le=MAX_EPOCHS, over=EPOCHS_BOUND)


def betas(setting_: str, values: Any) -> None:
    """Adam's two decay rates, each in [0, 1) as torch.optim.Adam requires: said at once,
    not by torch after the data has loaded."""
    if len(values) != 2 or not all(0.0 <= b < 1.0 for b in values):
        raise ConfigError(f"{setting_}={list(values)}: two decay rates, each in [0, 1)")


def section(prefix: str):
    """A frozen pydantic dataclass whose settings are named ``prefix`` + field
    (``train.``); building it refuses a bad value with :class:`ConfigError`, one line."""

    def make(cls: type) -> type:
        made = pydantic_dataclass(cls, frozen=True, config=CONFIG)
        made.__setting_prefix__ = prefix
        init = made.__init__
        names = [f.name for f in dataclasses.fields(made)]

        @functools.wraps(init)
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            # by name: a refusal then names the setting (TaskSpec("circle", column))
            if len(args) > len(names):
                raise TypeError(f"{cls.__name__}: {len(args)} values for {len(names)} settings")
            given = {**dict(zip(names, args, strict=False)), **kwargs}
            try:
                init(self, **given)
            except ValidationError as err:
                found = refusals(err, type(self), given)
                refused = ConfigError(min(found, key=lambda r: not r.shape).problem)
                refused.refusals = found  # the loader names the layer of a shape's fault
                raise refused from None

        made.__init__ = __init__
        return made

    return make


def renamed(cls: type, prefix: str) -> None:
    """Give a section built elsewhere (a method's settings) its settings' names."""
    cls.__setting_prefix__ = prefix


# --------------------------------------------------------------------------- refusals

SHAPE = frozenset(
    {
        "unexpected_keyword_argument",
        "extra_forbidden",
        "dataclass_type",
        "dataclass_exact_type",
        "tuple_type",
        "list_type",
        "too_short",
        "too_long",
        "string_type",
        "bool_type",
        "path_type",
        "missing_argument",
        "missing",
    }
)


class Refusal(typing.NamedTuple):
    """One refused value: its setting, what is wrong, and whether it is the value's shape
    (an unknown name, a section given a value, a list of the wrong length: said with the
    layer that wrote it) rather than the value itself."""

    setting: str
    problem: str  # the whole line: ``train.epochs=0: must be >= 1``
    shape: bool
    reason: str  # what is wrong, without the setting: ``must be >= 1``


def refusals(err: ValidationError, cls: type, given: Any) -> list[Refusal]:
    """Each of pydantic's errors of building ``cls`` from ``given`` (the settings as
    written), said in the config's words."""
    return [_said(e, cls, given) for e in err.errors()]


def _said(e: dict, cls: type, given: Any) -> Refusal:
    # a union's member is named in the location too (``function-before[...]``): not a setting
    e = {**e, "loc": tuple(p for p in e["loc"] if isinstance(p, int) or "[" not in p)}
    names = [part for part in e["loc"] if isinstance(part, str)]
    _, field, hint = _field(cls, names)
    setting = getattr(cls, "__setting_prefix__", "") + _named(given, e["loc"])
    value = _value(given, names, e)
    if _bare(hint) is float and type(value) is int and abs(value) <= 1e308:
        value = float(value)  # as the setting holds it: timeout_s=0 is 0.0
    reason, shape, named = _reason(e, hint, field, value, setting)
    if named:  # the value is not said (an unknown name, a number's text)
        return Refusal(setting, f"{setting}: {reason}", shape, reason)
    shown = repr(value) if e["type"] == "literal_error" else _shown(value)
    return Refusal(setting, f"{setting}={shown}: {reason}", shape, reason)


def _reason(e: dict, hint: Any, field: Any, value: Any, setting: str) -> tuple[str, bool, bool]:
    """What is wrong with ``value``, whether it is its shape, and whether the line names
    the setting alone (the reason says the value)."""
    kind = e["type"]
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        return "unknown setting", True, True
    if kind in ("dataclass_type", "dataclass_exact_type") and not isinstance(value, dict):
        example = _first_setting(hint)
        reason = (
            f"a section of settings, not one value; set its parts (e.g. {setting}.{example}=...)"
        )
        return reason, True, False
    if kind in ("tuple_type", "list_type") and isinstance(value, dict):
        return f"a list goes here, not a mapping ({value})", True, True
    if kind in ("too_short", "too_long", "missing") and isinstance(value, list | tuple):
        wanted = len(typing.get_args(_bare(hint)))
        return f"a list of {wanted} values expected, {len(value)} given", True, False
    return _value_reason(e, hint, field)


def _value_reason(e: dict, hint: Any, field: Any) -> tuple[str, bool, bool]:
    """:func:`_reason` of a value (not its shape)."""
    kind, given = e["type"], e["input"]
    if kind in ("int_type", "float_type", "float_parsing", "int_parsing"):
        if isinstance(given, list | dict | tuple):
            return "a list or mapping where a number goes", False, False
        if isinstance(given, float) and kind == "int_type":
            return "must be an integer, not a float", False, False
        what = "an integer" if kind.startswith("int") else "a number"
        return f"Value {given!r} is not {what}", True, True
    if kind == "finite_number":
        return "must be a finite number", False, False
    if kind == "literal_error":
        options = ", ".join(str(o) for o in typing.get_args(_bare(hint)))
        return f"must be one of {options}", False, False
    if kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        return _bound(field, kind), False, False
    if kind in ("bool_type", "bool_parsing"):
        return f"Value {given!r} is not true or false", True, True
    if kind in ("string_type",):
        return f"Value {given!r} is not a text", True, True
    return e["msg"], kind in SHAPE, False


def _named(given: Any, loc: tuple) -> str:
    """The dotted setting at ``loc``; an entry of a list of named sections by its name
    (``data.tasks.circle.value``), of other lists not at all (the list is the setting)."""
    parts, here = [], given
    for part in loc:
        if isinstance(part, int):
            item = here[part] if isinstance(here, list | tuple) and part < len(here) else None
            name = item.get("name") if isinstance(item, dict) else getattr(item, "name", None)
            if isinstance(name, str):
                parts.append(name)
            here = item
            continue
        parts.append(part)
        here = here.get(part) if isinstance(here, dict) else getattr(here, part, None)
    return ".".join(parts)


def _field(cls: type, names: list[str]):
    """The dataclass, pydantic field and type at ``names`` (a path of field names)."""
    owner, field, hint = cls, None, cls
    for name in names:
        fields = getattr(owner, "__pydantic_fields__", {})
        if name not in fields:
            return owner, None, None
        field = fields[name]
        hint = field.annotation
        owner = next((a for a in _options(hint) if dataclasses.is_dataclass(a)), None)
        if owner is None:
            break
    return owner, field, hint


def _options(hint: Any) -> tuple:
    return tuple(a for a in typing.get_args(hint) if a is not type(None)) or (hint,)


def _bare(hint: Any) -> Any:
    """The type without ``| None``."""
    options = _options(hint)
    return options[0] if len(options) == 1 else hint


def _first_setting(hint: Any) -> str:
    for option in _options(hint):
        if dataclasses.is_dataclass(option):
            return next(iter(f.name for f in dataclasses.fields(option)), "...")
    return "..."


def _value(given: Any, names: list[str], e: dict) -> Any:
    """The setting's whole value as written (a list whole, not the item at fault)."""
    value = given
    for name in names:
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = getattr(value, name, None)
        elif isinstance(value, dict):
            value = value.get(name)
        else:
            return e["input"]
    return value


def _shown(value: Any) -> str:
    """A value as the line shows it: a list as written, a long one cut short."""
    text = str(list(value) if isinstance(value, tuple) else value)
    return text if len(text) <= 120 else f"{text[:100]}..."


def _bound(field: Any, kind: str) -> str:
    """What the value breaks of the field's bounds: ``must be in 0..1``, ``must be in [0,
    1)``, ``must be > 0``, ... and why, or what the field says in its place."""
    extra = (field.json_schema_extra or {}) if field is not None else {}
    said = extra.get("said", {})
    limits = _limits(field)
    if not limits:
        return "out of its bounds"
    if "said" in said:
        return said["said"]
    if "over" in said:
        if kind.startswith("less"):
            return said["over"].format(bound=_figure(limits.get("le", limits.get("lt"))))
        limits = {k: v for k, v in limits.items() if k in ("ge", "gt")}
    why = f" ({said['why']})" if "why" in said else ""
    return f"must be {_range(limits)}{why}"


def _limits(field: Any) -> dict[str, float]:
    found: dict[str, float] = {}
    for meta in getattr(field, "metadata", ()):
        for name in ("ge", "gt", "le", "lt"):
            if getattr(meta, name, None) is not None:
                found[name] = getattr(meta, name)
    return found


def _range(limits: dict[str, float]) -> str:
    low = limits.get("ge", limits.get("gt"))
    high = limits.get("le", limits.get("lt"))
    if low is not None and high is not None:
        if "ge" in limits and "le" in limits:
            return f"in {_figure(low)}..{_figure(high)}"
        opening = "[" if "ge" in limits else "("
        closing = "]" if "le" in limits else ")"
        return f"in {opening}{_figure(low)}, {_figure(high)}{closing}"
    if low is not None:
        return f"{'>=' if 'ge' in limits else '>'} {_figure(low)}"
    return f"{'<=' if 'le' in limits else '<'} {_figure(high)}"


def _figure(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


# --------------------------------------------------------------------------- reading the model


def settings_of(cls: type, prefix: str = "") -> typing.Iterator[tuple[str, Any, Any]]:
    """``(dotted name, type, pydantic field)`` for every setting under ``cls``, sections
    walked into: what the settings reference and the sweep file's checks read."""
    for name, field in cls.__pydantic_fields__.items():
        listed = typing.get_origin(field.annotation) is tuple  # data.tasks: a list of them
        inner = [a for a in _options(field.annotation) if dataclasses.is_dataclass(a)]
        inner = [] if listed else inner
        if inner:
            yield from settings_of(inner[0], f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", field.annotation, field


def type_name(hint: Any) -> str:
    """A setting's type as a user writes it: ``int``, ``one of a, b``, ``[float, float]``,
    ``[int, ...]``, ``... or null``."""
    options = _options(hint)
    if len(options) < len(typing.get_args(hint)):  # X | None
        return " or ".join([*(type_name(o) for o in options), "null"])
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Annotated:
        return type_name(args[0])
    if origin is typing.Literal:
        return "one of " + ", ".join(str(a) for a in args)
    if origin is tuple:
        if args[1:] == (Ellipsis,):
            return f"[{type_name(args[0])}, ...]"
        return "[" + ", ".join(type_name(a) for a in args) + "]"
    if dataclasses.is_dataclass(hint):
        return "{" + ", ".join(f.name for f in dataclasses.fields(hint)) + "}"
    return {"Path": "path", "PosixPath": "path"}.get(getattr(hint, "__name__", "")) or str(
        getattr(hint, "__name__", hint)
    )


def bounds_of(field: Any) -> str:
    """A setting's bounds as its refusal says them (``>= 1``, ``in [0, 1)``), or ''."""
    limits = _limits(field)
    return _range(limits) if limits else ""


def section_of(hint: Any) -> type | None:
    """The section a field holds (its dataclass), None for a setting."""
    if typing.get_origin(hint) is tuple:
        return None
    return next((a for a in _options(hint) if dataclasses.is_dataclass(a)), None)


def type_problem(cls: type, name: str, value: Any) -> str | None:
    """What is wrong with the type of ``value`` for setting ``name`` of section ``cls``
    (its bounds and choices aside: a later layer of a config may still set another), in
    one line; None where the type fits. A list's items are checked with the whole config."""
    try:
        _adapter(cls, name).validate_python(value)
    except ValidationError as err:
        listed = typing.get_origin(cls.__pydantic_fields__[name].annotation) is tuple
        for e in err.errors():
            if not any(isinstance(part, int) for part in e["loc"]):  # an item: checked later
                loc = (name, *e["loc"]) if listed else (name,)  # not a union's member name
                return _said({**e, "loc": loc}, cls, {name: value}).problem
    return None


@functools.cache
def _adapter(cls: type, name: str) -> Any:
    field = cls.__pydantic_fields__[name]
    kept = [m for m in field.metadata if isinstance(m, Strict | BeforeValidator)]  # no bounds
    hint = Annotated[(_loose(field.annotation), *kept)] if kept else _loose(field.annotation)
    try:  # numbers read as text where text goes, as the sections do (CONFIG)
        return TypeAdapter(hint, config=ConfigDict(coerce_numbers_to_str=True))
    except PydanticUserError:  # a type with a config of its own (a list of sections)
        return TypeAdapter(hint)


def _loose(hint: Any) -> Any:
    """``hint`` with its choices as any value: a choice (``server_eval=true`` is ``on``) is
    checked once the layers are merged."""
    if typing.get_origin(hint) is typing.Literal:
        return str | bool
    options = typing.get_args(hint)
    if type(None) in options and len(options) == 2:
        return _loose(_options(hint)[0]) | None
    return hint
