"""The argparse pieces every verb shares: the help formatter, the parser class and the
``--crop`` argument type. Argparse only, so that ``fedlgr --help`` stays fast."""

from __future__ import annotations

import argparse


def crop(text: str) -> tuple[int | None, ...]:
    """``--crop 295,,1313,`` -> (295, None, 1313, None)."""
    parts = text.split(",")
    if len(parts) != 4:
        raise argparse.ArgumentTypeError(
            "expected LEFT,TOP,RIGHT,BOTTOM (leave one empty for an edge)"
        )
    try:
        return tuple(int(p) if p.strip() else None for p in parts)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"not a pixel position: {err}") from None


class HelpFormatter(argparse.HelpFormatter):
    """Every option's default in its help (argparse's ``ArgumentDefaultsHelpFormatter``
    without the noise of ``None``, ``False`` and ``[]``), and paragraphs of a description or
    epilog kept apart, and one that holds lines indented by two spaces (a listing) kept as
    written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            "%(default)" in text
            or default is None
            or default is False
            or default == []
            or default == argparse.SUPPRESS
            or not (action.option_strings or action.nargs in ("?", "*"))
        ):
            return text
        return f"{text} (default: %(default)s)"

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        blocks = []
        for block in text.split("\n\n"):
            if block.startswith("  ") or "\n  " in block:
                blocks.append("\n".join(indent + line for line in block.splitlines()))
            else:
                blocks.append(super()._fill_text(block, width, indent))
        return "\n\n".join(blocks)


class Parser(argparse.ArgumentParser):
    """An argument parser with :class:`HelpFormatter`, for the verbs too (sub-parsers are
    made of their parent's class)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)


Verbs = argparse._SubParsersAction  # what add_subparsers returns: a verb's add_parser adds to it
