"""docs/settings.md from the settings' declarations, ``uv run python -m
fedlgr.shell.config.reference > docs/settings.md``; a test checks that it is current."""

from __future__ import annotations

import yaml

from fedlgr.core.declare import bounds_of, settings_of, type_name
from fedlgr.core.settings import ExperimentConfig
from fedlgr.shell.config.export import _leaves, to_plain


def reference() -> str:
    """Every setting with its type, default, bounds and doc, from the settings' declarations."""
    defaults = dict(_leaves(to_plain(ExperimentConfig())))
    lines = [
        "# Settings",
        "",
        "Every setting, generated from its declaration in `fedlgr/core/settings/model.py` "
        "(a method's: `fedlgr/core/methods.py`) by `uv run python -m fedlgr.shell.config."
        "reference > docs/settings.md`. Set one in a config file (nested) or on the command "
        "line (`train.epochs=3`); `--print-config` shows a run's resolved values.",
    ]
    section = None
    for name, hint, field in settings_of(ExperimentConfig):
        here = name.rsplit(".", 1)[0] if "." in name else "(top level)"
        if here != section:
            section = here
            lines += [
                "",
                f"## {section}",
                "",
                "| setting | type | default | doc |",
                "|---|---|---|---|",
            ]
        kind = type_name(hint) + (f", {bounds_of(field)}" if bounds_of(field) else "")
        default = defaults.get(name)
        flow = {"default_flow_style": True, "sort_keys": False, "width": 10**6}
        shown = "null" if default is None else yaml.safe_dump(default, **flow)
        shown = shown.strip().removesuffix("...").strip()
        if callable(field.default_factory) and not isinstance(field.default_factory, type):
            shown = "(doc)"  # chosen where the run starts ($FEDLGR_CACHE_DIR, ...)
        doc = (field.description or "").replace("|", "\\|")
        lines.append(f"| `{name}` | {kind} | `{shown}` | {doc} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(reference(), end="")
