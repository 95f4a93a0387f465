"""A report's Markdown tables, and those a script prints, read back."""

from __future__ import annotations


def markdown_blocks(path) -> dict[str, tuple[list[str], dict[str, list[str]]]]:
    """``{block title: (header, {row label: cells})}`` from a report's Markdown file."""
    blocks, title = {}, None
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("**") and line.endswith("**"):
            title = line.strip("*")
        elif line.startswith("| ") and title is not None and not line.startswith("| ---"):
            cells = line[2:-2].split(" | ")
            if title not in blocks:
                blocks[title] = (cells, {})
            else:
                blocks[title][1][cells[0]] = cells[1:]
    return blocks


def parse(cell: str) -> tuple[str | None, str]:
    """(number as shown or None, mark) of a Markdown cell."""
    number = cell.split(" (")[0]
    if number == "—":
        return None, ""
    if number.startswith("**"):
        return number.strip("*"), "best"
    if number.startswith("["):
        return number.strip("[]"), "second"
    return number, ""


def printed_rows(stdout: str, head: str) -> list[list[str]]:
    """The rows (cells) of the Markdown table a script printed whose header line starts
    with ``head``."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(head))
    assert set(lines[start + 1].replace("|", "")) == {"-"}, lines[start + 1]
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip("|").split("|")])
    return rows
