"""A :class:`~fedlgr.shell.report.tables.Table` as Markdown and LaTeX, the best of a column
**bold** and the second-best [bracketed] as in the paper, and as CSV, unrounded and unmarked."""

from __future__ import annotations

import csv
import io
from collections.abc import Callable
from itertools import groupby

from fedlgr.shell.report.tables import Cell, Table

MISSING = "—"
ARROWS = {True: " ▼", False: " ▲", None: ""}
TEX_ARROWS = {True: r" $\blacktriangledown$", False: r" $\blacktriangle$", None: ""}
# How a cell's best and second-best values and its FedRoot reduction (down, up) are written.
MD_STYLE = {"best": "**{}**", "second": "[{}]", "down": "(▼ {:.1f}%)", "up": "(▲ {:.1f}%)"}
TEX_STYLE = {
    "best": r"\textbf{{{}}}",
    "second": "[{}]",
    "down": r"($\blacktriangledown$~{:.1f}\%)",
    "up": r"($\blacktriangle$~{:.1f}\%)",
}


def to_markdown(table: Table) -> str:
    headers = [table.row_header]
    headers += [" · ".join(c.header) + ARROWS[c.lower_is_better] for c in table.columns]
    lines = [f"## Table {table.number}: {table.caption}", ""]
    for block in table.blocks:
        lines += [f"**{block.title}**", "", md_row(headers)]
        lines.append(md_row(["---"] + ["---:"] * len(table.columns)))
        for label, cells in block.rows:
            label += ARROWS[table.row_direction]
            lines.append(md_row([label] + [_cell(c, MD_STYLE) for c in cells]))
        lines.append("")
    for note in table.notes:  # separate paragraphs
        lines += [note, ""]
    return "\n".join(lines)


def md_row(cells: list[str]) -> str:
    return "| " + " | ".join(c.replace("|", r"\|") for c in cells) + " |"


def _cell(cell: Cell, style: dict[str, str], detail: Callable[[str], str] = str) -> str:
    """The value marked in ``style``, its ``detail`` (± and n) and its FedRoot reduction."""
    if cell.value is None:
        return MISSING
    text = style.get(cell.mark, "{}").format(cell.shown()) + detail(cell.detail())
    if cell.reduction is not None:
        text += " " + style["down" if cell.reduction >= 0 else "up"].format(abs(cell.reduction))
    return text


def to_latex(table: Table) -> str:
    """A ``table*`` with booktabs rules (needs ``\\usepackage{booktabs,amssymb}``)."""
    columns = table.columns
    width = len(columns) + 1
    spec = "l|" + "|".join("c" * len(list(g)) for _, g in groupby(columns, key=lambda c: c.group))
    lines = [
        f"% Table {table.number}, written by fedlgr report; needs booktabs and amssymb.",
        r"\begin{table*}[t]",
        r"\centering",
        rf"\caption{{{_tex(table.caption)}}}",
        rf"\label{{tab:{table.name}}}",
        rf"\begin{{tabular}}{{{spec}}}\toprule",
    ]
    for level in range(1, max(len(c.header) for c in columns)):  # the headings above the last
        cells, done = [""], 0
        for key, group in groupby(columns, key=lambda c: c.header[:level]):
            n = len(list(group))
            done += n
            rule = "|" if done < len(columns) else ""
            cells.append(rf"\multicolumn{{{n}}}{{c{rule}}}{{\textit{{{_tex(key[-1])}}}}}")
        lines.append(" & ".join(cells) + r"\\")
    heads = [_tex(c.header[-1]) + TEX_ARROWS[c.lower_is_better] for c in columns]
    lines.append(" & ".join([_tex(table.row_header), *heads]) + r"\\\midrule")
    for k, block in enumerate(table.blocks):
        lines.append(rf"\multicolumn{{{width}}}{{c}}{{\textit{{{_tex(block.title)}}}}}\\\midrule")
        for label, cells in block.rows:
            label = _tex(label) + TEX_ARROWS[table.row_direction]
            lines.append(" & ".join([label, *map(_tex_cell, cells)]) + r"\\")
        lines.append(r"\bottomrule" if k == len(table.blocks) - 1 else r"\midrule")
    lines.append(r"\end{tabular}")
    lines += [r"\par\smallskip{\footnotesize " + _tex_note(n) + "}" for n in table.notes]
    lines += [r"\end{table*}", ""]
    return "\n".join(lines)


def _tex_cell(cell: Cell) -> str:
    return _cell(cell, TEX_STYLE, lambda detail: _tex(detail).replace("±", r"$\pm$"))


def _tex_note(note: str) -> str:
    """A Markdown note in LaTeX: **bold** as \\textbf, `code` as plain text, the arrows."""
    parts = _tex(note.replace("`", "")).split("**")
    text = "".join(rf"\textbf{{{p}}}" if k % 2 else p for k, p in enumerate(parts))
    return text.replace("▼", r"$\blacktriangledown$").replace("▲", r"$\blacktriangle$")


_TEX_SPECIAL = str.maketrans(
    {ch: "\\" + ch for ch in "&%$#_{}"}
    | {"\\": r"\textbackslash{}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}
)


def _tex(text: str) -> str:
    return text.translate(_TEX_SPECIAL)


def to_csv(table: Table) -> str:
    header = [table.block_header, table.row_header.lower()]
    for column in table.columns:
        header += [column.key, f"{column.key} std", f"{column.key} n"]
        if column.reduces:
            header.append(f"{column.key} reduction %")
    rows = [header]
    for block in table.blocks:
        for label, cells in block.rows:
            row = [block.title, label]
            for column, cell in zip(table.columns, cells, strict=True):
                row += [csv_number(cell.value), csv_number(cell.std), str(cell.runs)]
                if column.reduces:
                    row.append(csv_number(cell.reduction))
            rows.append(row)
    return csv_text(rows)


def csv_text(rows: list[list[str]]) -> str:
    buffer = io.StringIO()
    csv.writer(buffer, lineterminator="\n").writerows(rows)
    return buffer.getvalue()


def csv_number(value: float | None) -> str:
    return "" if value is None else repr(float(value))
