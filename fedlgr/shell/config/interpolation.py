"""The ``${...}`` a config may hold: a reference to another setting, or an environment variable
FEDLGR_* (optionally with a default). All else is refused in every layer before anything resolves,
since a resolver can read or build anything; each failure is one line."""

from __future__ import annotations

import re
from typing import Any

from fedlgr.errors import ConfigError, first_line
from fedlgr.shell.config.written import plain, strings

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
    checked against ``_ALLOWED`` before anything is resolved."""
    found = {}
    for key, value in strings(plain(node)):
        for start in (m.start() for m in re.finditer(r"\$\{", value)):
            escapes = len(value[:start]) - len(value[:start].rstrip("\\"))
            if escapes % 2 == 0 and not re.match(_ALLOWED, value[start:]):
                raise ConfigError(f"{source}: {key}={value!r}: {_POLICY}")
        if "${" in value:
            found[key] = (source, value)
    return found


def resolve(merged: Any, interpolated: dict[str, tuple[Any, str]]) -> None:
    """Resolve each ``${...}`` once, so that a reference to nothing, a loop, an unset
    variable or a value of the wrong type is one line naming the setting and its layer."""
    # lazy: omegaconf is imported once a config is loaded, not by fedlgr --help
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    for key, (source, value) in interpolated.items():
        try:
            OmegaConf.select(merged, key)
        except OmegaConfBaseException as err:
            raise ConfigError(f"{source}: {key}={value!r}: {first_line(err)}") from None
