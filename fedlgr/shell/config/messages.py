"""OmegaConf's errors as one line in the config's words: the setting at fault named (an unknown one
with the closest known names), never OmegaConf's internals or a traceback."""

from __future__ import annotations

import difflib
from typing import Any

from fedlgr.errors import first_line
from fedlgr.shell.config.export import known_settings
from fedlgr.shell.config.written import lookup


def omegaconf_message(err: Exception) -> str:
    key = getattr(err, "full_key", None)
    first = first_line(err)
    return f"{key}: {first}" if key else first


def container_mismatch(merged: Any, written: dict, prefix: str = "") -> str | None:
    """The setting given a mapping where a list goes, or a list where a section goes: what
    OmegaConf's merge refuses with a bare ``TypeError``."""
    # lazy: omegaconf is imported once a config is loaded, not by fedlgr --help
    from omegaconf import DictConfig, ListConfig, OmegaConf
    from omegaconf.tupleconfig import TupleConfig

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
    matcher = difflib.SequenceMatcher(b=key)
    scores = []
    for name in known:
        matcher.set_seq1(name)
        scores.append((matcher.ratio(), name))
    close = [(r, n) for r, n in sorted(scores, reverse=True)[:2] if r >= 0.6]
    return [n for r, n in close if r >= close[0][0] - 0.05]  # a far second is noise


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
