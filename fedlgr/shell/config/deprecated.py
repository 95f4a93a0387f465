"""The old names of the methods' settings, still read for one more release: up to fedlgr
0.x they were prefixed fields of ``federated``/``continual`` (``continual.lgr_hidden`` is
now ``continual.lgr.hidden``, ``federated.server_lr`` is ``federated.opt.lr``). A layer
that uses them is read with the new names and one line on stderr naming each."""

from __future__ import annotations

import dataclasses
import sys
from typing import Any

from fedlgr.core.methods import CONTINUAL, STRATEGIES
from fedlgr.errors import ConfigError
from fedlgr.shell.config.written import plain


def _deprecated_names() -> dict[tuple[str, str], str]:
    """``(section, old flat name) -> new name``."""
    old = {("federated", f"server_{f}"): f"opt.{f}" for f in ("lr", "betas", "tau")}
    for section, registry, keys in (
        ("federated", STRATEGIES, ("prox", "distill")),
        ("continual", CONTINUAL, ("ewc", "si", "mas", "nr", "lgr")),
    ):
        for key in keys:
            for f in dataclasses.fields(registry[key].settings):
                old[(section, f"{key}_{f.name.rstrip('_')}")] = f"{key}.{f.name}"
    return old


DEPRECATED = _deprecated_names()


def renamed(source: Any, node: Any) -> Any:
    """The layer with the deprecated flat method settings moved to their sections."""
    # lazy: omegaconf is imported once a config is loaded, not by fedlgr --help
    from omegaconf import OmegaConf

    values = plain(node)
    moved = []
    for section in ("federated", "continual"):
        here = values.get(section) if isinstance(values, dict) else None
        if isinstance(here, dict):
            moved += _move(source, section, here)
    if not moved:
        return node
    print(
        f"fedlgr: {source}: deprecated setting names, read for one more release: "
        + "; ".join(moved),
        file=sys.stderr,
    )
    return OmegaConf.create(values)


def _move(source: Any, section: str, here: dict) -> list[str]:
    """Move the deprecated names of one section's values (``here``, changed in place) to
    their new places; what was moved, in words."""
    moved = []
    for name in [n for n in here if (section, n) in DEPRECATED]:
        new = DEPRECATED[(section, name)]
        group, _, leaf = new.partition(".")
        target = here.setdefault(group, {})
        if not isinstance(target, dict):
            continue  # e.g. continual.lgr=5: the merge names the bad value
        if leaf in target:
            raise ConfigError(
                f"{source}: {section}.{name} and {section}.{new} are one setting (the "
                f"first is its deprecated name), given twice: keep {section}.{new}"
            )
        target[leaf] = here.pop(name)
        moved.append(f"{section}.{name} is now {section}.{new}")
    return moved
