"""How a setting is declared: a field of a frozen pydantic dataclass with its type, its
default, its bounds and a one-line doc (:func:`setting`); and pydantic's refusals said in
the config's words, one line naming the full setting (``federated.prox.mu=-1: must be >=
0``). Pydantic types and bounds the values; the rules a bound cannot say (one setting
against another) are each section's ``__post_init__``, which raises :class:`ConfigError`.

Integers are strict (``10.0`` where a count goes is refused, not rounded) and floats
finite, as OmegaConf and fedlgr's own checks had them before."""

from __future__ import annotations

import dataclasses
import functools
import typing
from typing import Annotated, Any

from pydantic import ConfigDict, Field, Strict, ValidationError
from pydantic.dataclasses import dataclass as pydantic_dataclass

from fedlgr.errors import ConfigError

Int = Annotated[int, Strict()]  # a count: 10.0 or "10" is refused, not converted
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


def section(prefix: str):
    """A frozen pydantic dataclass whose settings are named ``prefix`` + field
    (``train.``); building it refuses a bad value with :class:`ConfigError`, one line."""

    def make(cls: type) -> type:
        made = pydantic_dataclass(cls, frozen=True, config=CONFIG)
        made.__setting_prefix__ = prefix
        init = made.__init__

        @functools.wraps(init)
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            try:
                init(self, *args, **kwargs)
            except ValidationError as err:
                found = refusals(err, type(self), kwargs)
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
    problem: str
    shape: bool


def refusals(err: ValidationError, cls: type, given: Any) -> list[Refusal]:
    """Each of pydantic's errors of building ``cls`` from ``given`` (the settings as
    written), said in the config's words."""
    return [_said(e, cls, given) for e in err.errors()]


def _said(e: dict, cls: type, given: Any) -> Refusal:
    names = [part for part in e["loc"] if isinstance(part, str)]
    _, field, hint = _field(cls, names)
    setting = getattr(cls, "__setting_prefix__", "") + ".".join(names)
    value = _value(given, names, e)
    if _bare(hint) is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)  # as the setting holds it: timeout_s=0 is 0.0
    kind = e["type"]
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        return Refusal(setting, f"{setting}: unknown setting", True)
    if kind in ("dataclass_type", "dataclass_exact_type") and not isinstance(value, dict):
        example = _first_setting(hint)
        return Refusal(
            setting,
            f"{setting}={_shown(value)}: a section of settings, not one value; set its parts "
            f"(e.g. {setting}.{example}=...)",
            True,
        )
    if kind in ("tuple_type", "list_type") and isinstance(value, dict):
        return Refusal(setting, f"{setting}: a list goes here, not a mapping ({value})", True)
    if kind in ("too_short", "too_long", "missing") and isinstance(value, list | tuple):
        wanted = len(typing.get_args(_bare(hint)))
        return Refusal(
            setting,
            f"{setting}={_shown(value)}: a list of {wanted} values expected, {len(value)} given",
            True,
        )
    if kind in ("int_type", "float_type", "float_parsing", "int_parsing"):
        if isinstance(e["input"], list | dict | tuple):
            return Refusal(
                setting, f"{setting}={_shown(value)}: a list or mapping where a number goes", False
            )
        if isinstance(e["input"], float) and kind == "int_type":
            return Refusal(
                setting, f"{setting}={_shown(value)}: must be an integer, not a float", False
            )
        what = "an integer" if kind.startswith("int") else "a number"
        return Refusal(setting, f"{setting}: Value {e['input']!r} is not {what}", True)
    if kind == "finite_number":
        return Refusal(setting, f"{setting}={_shown(value)}: must be a finite number", False)
    if kind == "literal_error":
        options = ", ".join(str(o) for o in typing.get_args(_bare(hint)))
        return Refusal(setting, f"{setting}={value!r}: must be one of {options}", False)
    if kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        return Refusal(setting, f"{setting}={_shown(value)}: {_bound(field, kind)}", False)
    shape = kind in SHAPE
    return Refusal(setting, f"{setting}={_shown(value)}: {e['msg']}", shape)


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
    if isinstance(value, tuple):
        value = list(value)
    return str(value)


def _bound(field: Any, kind: str) -> str:
    """What the value breaks of the field's bounds: ``must be in 0..1``, ``must be in [0,
    1)``, ``must be > 0``, ... and why, or what the field says in its place."""
    extra = (field.json_schema_extra or {}) if field is not None else {}
    said = extra.get("said", {})
    limits = _limits(field)
    if "said" in said:
        return said["said"]
    if "over" in said:
        if kind.startswith("less"):
            return said["over"].format(bound=_number(limits.get("le", limits.get("lt"))))
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
            return f"in {_number(low)}..{_number(high)}"
        opening = "[" if "ge" in limits else "("
        closing = "]" if "le" in limits else ")"
        return f"in {opening}{_number(low)}, {_number(high)}{closing}"
    if low is not None:
        return f"{'>=' if 'ge' in limits else '>'} {_number(low)}"
    return f"{'<=' if 'le' in limits else '<'} {_number(high)}"


def _number(value: float) -> str:
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
