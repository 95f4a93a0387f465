"""A config layer's values as written (plain dicts and lists, ``${...}`` unresolved) and the walks
over them: checks read these, never resolved values, so nothing resolves before it is allowed."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any


def plain(node: Any) -> Any:
    """A layer's values as written: dicts and lists, ``${...}`` left unresolved."""
    # lazy: omegaconf is imported once a config is loaded, not by fedlgr --help
    from omegaconf import OmegaConf

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
