"""Value checks: the rules every setting's value follows, each refusal one line that
names the setting (``train.epochs=0: must be >= 1``). The config's dataclasses call
them as they are built (each section's rules are in :mod:`.settings`), a method's settings
are checked against the bounds their fields declare (:func:`check_settings`), so the
round's core trusts the config it is given."""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing

from fedlgr.core.methods import Bounds, bounds
from fedlgr.errors import ConfigError

# numpy's and Lightning's seeding take 32-bit seeds
SEED_LIMIT = 2**32


def check_numbers(prefix: str, settings) -> None:
    """Refuse NaN and infinite floats, and floats where the field's type says ``int``, in
    every field of the dataclass ``settings`` (``prefix`` + field name is the setting).

    OmegaConf checks the types of what it loads, but lets ``.nan`` and ``.inf`` through and
    code may build the dataclasses directly; a NaN slips past every ``value < 0`` test.
    """
    hints = _type_hints(type(settings))
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        problem = _number_problem(hints[f.name], value)
        if problem is not None:
            shown = list(value) if isinstance(value, tuple) else value
            raise ConfigError(f"{prefix}{f.name}={shown}: {problem}")


_type_hints = functools.cache(typing.get_type_hints)


def _number_problem(hint, value) -> str | None:
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(hint) if a is not type(None)]
        return None if value is None or len(options) != 1 else _number_problem(options[0], value)
    if origin is tuple and isinstance(value, tuple | list):
        args = typing.get_args(hint)
        items = args[:1] * len(value) if args[1:] == (Ellipsis,) else args
        problems = (_number_problem(a, v) for a, v in zip(items, value, strict=False))
        return next((p for p in problems if p is not None), None)
    if hint in (int, float) and isinstance(value, list | tuple | dict):
        # OmegaConf does not type what a typed tuple holds: model.mlp_hidden=[[16]] would
        # fail later as "'<' not supported between instances of 'list' and 'int'"
        return "a list or mapping where a number goes"
    if hint is int and isinstance(value, float):
        return "must be an integer, not a float"
    if isinstance(value, float) and not math.isfinite(value):
        return "must be a finite number"
    return None


def check_seed(setting: str, value: int) -> None:
    if not 0 <= value < SEED_LIMIT:
        raise ConfigError(
            f"{setting}={value}: must be in 0..{SEED_LIMIT - 1} (numpy's and Lightning's "
            "seeding take 32-bit seeds)"
        )


def machine_memory() -> int:
    """This machine's memory in bytes (``psutil.virtual_memory().total``)."""
    import psutil  # lazy: psutil is heavy, and the config loads before any run (fedlgr --help)

    return psutil.virtual_memory().total


def format_bytes(n: float) -> str:
    """``3.2 GB``: decimal units, as ``free`` and ``df -H`` print them."""
    units = ("B", "kB", "MB", "GB", "TB")
    k = 0
    while n >= 1000 and k < len(units) - 1:
        n, k = n / 1000, k + 1
    return f"{n:.0f} B" if k == 0 else f"{n:.1f} {units[k]}"


def choice(setting: str, value: str, options: tuple[str, ...]) -> None:
    if value not in options:
        raise ConfigError(f"{setting}={value!r}: must be one of {', '.join(options)}")


def positive(setting: str, value: int) -> None:
    if value < 1:
        raise ConfigError(f"{setting}={value}: must be >= 1")


MAX_EPOCHS = 100_000


def epochs(setting: str, value: int | None, least: int = 1) -> None:
    """A count of epochs: ``least`` or more, and at most MAX_EPOCHS - a fixed bound, so
    that no config (a robot's included, sent by its server) asks for a run that never
    ends; the paper's longest is 300."""
    if value is None:
        return
    if value < least:
        raise ConfigError(f"{setting}={value}: must be >= {least}")
    if value > MAX_EPOCHS:
        raise ConfigError(
            f"{setting}={value}: at most {MAX_EPOCHS} epochs (a fixed bound; the paper's "
            "longest is the VAE's 300)"
        )


def nonnegative(setting: str, value: float) -> None:
    if value < 0:
        raise ConfigError(f"{setting}={value}: must be >= 0")


def betas(setting: str, values) -> None:
    """Adam's two decay rates, each in [0, 1) as torch.optim.Adam requires: said at once,
    not by torch after the data has loaded."""
    if len(values) != 2 or not all(0.0 <= b < 1.0 for b in values):
        raise ConfigError(f"{setting}={list(values)}: two decay rates, each in [0, 1)")


def check_settings(section: str, settings) -> None:
    """A method's settings (``section``: ``continual.lgr``): numbers, then each field's
    declared :class:`~fedlgr.core.methods.Bounds`."""
    check_numbers(f"{section}.", settings)
    for f in dataclasses.fields(settings):
        check_bounds(f"{section}.{f.name}", getattr(settings, f.name), bounds(f))


def check_bounds(setting: str, value, rule: Bounds) -> None:
    """``value`` within ``rule``, else one line naming ``setting``."""
    if value is None:
        return
    if rule.choices:
        choice(setting, value, rule.choices)
    if rule.kind == "betas":
        betas(setting, value)
    problem = _bound_problem(value, rule)
    if problem:
        reason = f" ({rule.reason})" if rule.reason else ""
        raise ConfigError(f"{setting}={value}: must be {problem}{reason}")
    if rule.kind == "epochs":
        epochs(setting, value, least=1 if rule.least is None else int(rule.least))


def _bound_problem(value, rule: Bounds) -> str | None:
    """What ``value`` breaks of the numeric bounds: ``in 0..1``, ``in [0, 1)``, ``> 0``,
    ``>= 0``; None where it keeps them."""
    low, high = rule.least if rule.least is not None else rule.above, None
    high = rule.most if rule.most is not None else rule.below
    low_ok = (rule.least is None or value >= rule.least) and (
        rule.above is None or value > rule.above
    )
    high_ok = (rule.most is None or value <= rule.most) and (
        rule.below is None or value < rule.below
    )
    if low_ok and high_ok:
        return None
    if low is not None and high is not None:
        if rule.least is not None and rule.most is not None:
            return f"in {_number(low)}..{_number(high)}"
        opening = "[" if rule.least is not None else "("
        closing = "]" if rule.most is not None else ")"
        return f"in {opening}{_number(low)}, {_number(high)}{closing}"
    if low is not None:
        return f"{'>=' if rule.least is not None else '>'} {_number(low)}"
    return f"{'<=' if rule.most is not None else '<'} {_number(high)}"


def _number(value: float) -> str:
    return f"{value:g}"
