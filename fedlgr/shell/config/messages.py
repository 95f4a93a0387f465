"""OmegaConf's errors as one line in the config's words: the setting at fault named (an
unknown one with the closest known names), never OmegaConf's internals ("Merge error: int
is not a subclass of TrainConfig", ``$VALUE``, a bare ``TypeError``) or a traceback."""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterator
from typing import Any

from fedlgr.errors import first_line
from fedlgr.shell.config.export import known_settings
from fedlgr.shell.config.written import lookup


def omegaconf_message(err: Exception) -> str:
    key = getattr(err, "full_key", None)
    first = first_line(err)
    return f"{key}: {first}" if key else first


def merge_message(err: Exception, merged: Any, node: Any) -> str:
    """:func:`omegaconf_message`, naming the setting and value at fault where OmegaConf's
    message does not (a list item of the wrong type: "Value '$VALUE' of type ..."): each
    setting of ``node`` is merged alone until one fails."""
    # lazy: omegaconf is imported once a config is loaded, not by fedlgr --help
    from omegaconf import OmegaConf
    from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

    if isinstance(err, ConfigKeyError) and getattr(err, "full_key", None):
        return unknown_setting(err.full_key, OmegaConf.to_container(node, resolve=False))
    if getattr(err, "full_key", None):
        return omegaconf_message(err)
    for key, value in _leaves(OmegaConf.to_container(node, resolve=False)):
        try:
            OmegaConf.merge(merged, _alone(key, value))
        except OmegaConfBaseException as one:
            return f"{key}={value!r}: {_plain_reason(one, key, merged)}"
    return omegaconf_message(err)


def _leaves(value: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``(dotted key, value)`` for every setting (not section) of plain ``value``."""
    if isinstance(value, dict):
        for key, inner in value.items():
            yield from _leaves(inner, f"{prefix}{key}.")
    else:
        yield prefix[:-1], value


def _alone(key: str, value: Any) -> dict:
    """The one setting ``key=value`` as nested mappings."""
    single: dict = {}
    *parents, last = key.split(".")
    here = single
    for part in parents:
        here = here.setdefault(part, {})
    here[last] = value
    return single


def _plain_reason(err: Exception, key: str, merged: Any) -> str:
    """OmegaConf's reason a value cannot go at ``key``, in the config's words where its own
    names its internals ("Merge error: int is not a subclass of TrainConfig", "TupleConfig
    length 1 does not match type hint length 2")."""
    # lazy: omegaconf is imported once a config is loaded, not by fedlgr --help
    from omegaconf import DictConfig, OmegaConf

    text = first_line(err).replace("Value '$VALUE' of type '$VALUE_TYPE'", "a value")
    here = OmegaConf.select(merged, key, throw_on_missing=False)
    if isinstance(here, DictConfig) and text.startswith("Merge error:"):
        first = next(iter(here), "...")
        return f"a section of settings, not one value; set its parts (e.g. {key}.{first}=...)"
    if found := re.match(r"TupleConfig length (\d+) does not match type hint length (\d+)", text):
        given, wanted = found.groups()
        return f"a list of {wanted} values expected, {given} given"
    return text


def container_mismatch(merged: Any, written: dict, prefix: str = "") -> str | None:
    """The setting given a mapping where a list goes, or a list where a section goes: what
    OmegaConf's merge refuses with a bare ``TypeError`` (``train.betas: {a: 1}`` would be a
    traceback)."""
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
    """``KEY: unknown setting; did you mean NAME?`` - the closest known settings to what was
    written (the whole dotted name, so ``train.learning_rate`` finds ``train.lr_root``).
    ``key`` is the first unknown part; a section written under it is matched by its
    setting when it holds one (``trian: {lr_top: 1}`` is ``trian.lr_top``)."""
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
