"""A config layer's values as written (``${...}`` unresolved) and the ``${...}`` they may hold:
another setting or a FEDLGR_* variable, checked in every layer before anything resolves."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

from fedlgr.errors import ConfigError


def plain(node: Any) -> Any:
    """A layer's values as written: dicts and lists, ``${...}`` left unresolved."""
    from omegaconf import OmegaConf  # lazy: fedlgr --help reads this module without OmegaConf

    return OmegaConf.to_container(node, resolve=False)


def lookup(values: Any, key: str) -> Any:
    """The raw value at dotted ``key`` in a layer's values, None where there is none."""
    for part in key.split("."):
        if not isinstance(values, dict) or part not in values:
            return None
        values = values[part]
    return values


def strings(values: Any, key: str = "", keys: bool = False) -> Iterator[tuple[str, str]]:
    """``(dotted key, string)`` for every string value (and with ``keys``, every key) in
    plain ``values``; list items as ``key[i]``."""
    if isinstance(values, dict):
        for name, value in values.items():
            if keys and isinstance(name, str):
                yield f"{key}.{name}" if key else name, name
            yield from strings(value, f"{key}.{name}" if key else str(name), keys)
    elif isinstance(values, list | tuple):
        for i, value in enumerate(values):
            yield from strings(value, f"{key}[{i}]", keys)
    elif isinstance(values, str):
        yield key, values


_REFERENCE = r"\.*[A-Za-z_][\w-]*(?:\.[\w-]+|\[\d+\])*"
_FEDLGR_ENV = r"oc\.env:FEDLGR_\w+(?:,[\w ./:@+-]*)?"
_ALLOWED = rf"\$\{{(?:{_REFERENCE}|{_FEDLGR_ENV})\}}"
_POLICY = (
    "a config's ${...} may name another setting (${data.clients}) or an environment "
    "variable FEDLGR_* (${oc.env:FEDLGR_DATA}), nothing else (docs/methods.md, "
    "'Running experiments')"
)


def check_interpolations(source: Any, node: Any) -> dict[str, tuple[Any, str]]:
    """``{key: (source, value)}`` for every value holding ``${...}`` in one layer, each
    checked against ``_ALLOWED`` before anything is resolved (a resolver can read or build
    anything)."""
    found = {}
    for key, value in strings(plain(node)):
        for start in (m.start() for m in re.finditer(r"\$\{", value)):
            escapes = len(value[:start]) - len(value[:start].rstrip("\\"))
            if escapes % 2 == 0 and not re.match(_ALLOWED, value[start:]):
                raise ConfigError(f"{source}: {key}={value!r}: {_POLICY}")
        if "${" in value:
            found[key] = (source, value)
    return found
