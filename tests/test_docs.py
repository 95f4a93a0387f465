"""The README and the pages in docs/: short README, links that resolve, and every ``fedlgr``
command in a shell block parses with fedlgr's own parser, its config and overrides load.

A command line is a line of a fenced ```bash / ```sh / ```console block that runs
``fedlgr VERB ...`` (after ``uv run``, ``python -m`` and ``NAME=value`` assignments; lines
ending in ``\\`` joined; ``# comments`` stripped). ``for VAR in A B; do`` loops are
expanded. Placeholders (``$VAR``, ``<x>``, ``CONFIG``, ``key=value``, ``...``, and the
brackets of ``[--size 128]``) may stand for arguments: they parse as strings and are left
out of the config check. The checks take a few seconds: no network, no training, no torch
(the suite's conftest imports torch, which takes longer).
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from fedlgr.errors import FedlgrError
from fedlgr.shell.cli import parse
from fedlgr.shell.cli.run import split_config_and_overrides
from fedlgr.shell.config import find_config, load_config

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOC_PAGES = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOC_PAGES]
SHELLS = {"bash", "sh", "shell", "console"}
README_MAX_LINES = 200

# Command lines whose config cannot load in a test (a file that cannot exist here), by a
# piece of the command: each with its reason. Kept small; a stale entry fails.
CONFIG_SKIPS: dict[str, str] = {}


def rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def fenced_blocks(text: str):
    """``(language, first line number of the body, body lines)`` of each fenced block."""
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        opening = re.match(r"^\s*(```+|~~~+)\s*([\w+-]*)", lines[i])
        if not opening:
            i += 1
            continue
        fence, lang = opening.group(1), opening.group(2).lower()
        body_start = i + 1
        j = body_start
        while j < len(lines) and not lines[j].strip().startswith(fence):
            j += 1
        yield lang, body_start + 1, lines[body_start:j]
        i = j + 1


def prose_lines(text: str):
    """``(line number, line)`` outside fenced blocks."""
    fenced = set()
    for _, start, body in fenced_blocks(text):
        fenced.update(range(start - 1, start + len(body) + 1))
    for number, line in enumerate(text.splitlines(), 1):
        if number not in fenced:
            yield number, line


def strip_comment(line: str) -> str:
    """The line without a shell comment: ``#`` at a word's start, outside quotes."""
    quote = None
    for i, char in enumerate(line):
        if quote:
            if char == quote:
                quote = None
        elif char in "'\"":
            quote = char
        elif char == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip()
    return line.rstrip()


@dataclass
class Command:
    page: str
    line: int
    text: str
    loops: dict[str, list[str]] = field(default_factory=dict)

    @property
    def id(self) -> str:
        return f"{self.page}:{self.line}"


def shell_lines(path: Path):
    """Each logical line of the page's shell blocks, with the loops it sits in."""
    for lang, start, body in fenced_blocks(path.read_text(encoding="utf-8")):
        if lang not in SHELLS:
            continue
        loops: dict[str, list[str]] = {}
        pending, first = "", None
        for offset, raw in enumerate(body):
            line = raw.rstrip()
            if lang == "console":
                line = re.sub(r"^\s*\$\s+", "", line)
            if first is None:
                first = start + offset
            if line.endswith("\\"):
                pending += line[:-1] + " "
                continue
            text, number = strip_comment(pending + line).strip(), first
            pending, first = "", None
            loop = re.fullmatch(r"for (\w+) in (.+?);\s*do", text)
            if loop:
                loops[loop.group(1)] = loop.group(2).split()
            elif text == "done" and loops:
                loops.popitem()
            elif text:
                yield Command(rel(path), number, text, dict(loops))


def fedlgr_argv(tokens: list[str]) -> list[str] | None:
    """The arguments after ``fedlgr`` if the line runs it, else None."""
    while tokens and re.fullmatch(r"[A-Za-z_]\w*=.*", tokens[0]):
        tokens = tokens[1:]  # NAME=value before the command
    if tokens[:2] == ["uv", "run"]:
        tokens = tokens[2:]
    if len(tokens) > 2 and tokens[0].startswith("python") and tokens[1:3] == ["-m", "fedlgr"]:
        return tokens[3:]
    return tokens[1:] if tokens[:1] == ["fedlgr"] else None


def expansions(command: Command) -> list[list[str]]:
    """The line's tokens, once per value of each loop variable it uses."""
    variants = [command.text]
    for name, values in command.loops.items():
        if f"${name}" in command.text or f"${{{name}}}" in command.text:
            variants = [
                re.sub(rf"\$(?:{name}\b|\{{{name}\}})", value, v)
                for v in variants
                for value in values
            ]
    return [shlex.split(v) for v in variants]


def words(text: str) -> list[str]:
    """The shell words of a line; an unbalanced quote gives none (a fedlgr line with one is
    still collected, and fails in its test with shlex's error)."""
    try:
        return shlex.split(text)
    except ValueError:
        return []


def fedlgr_commands() -> list[Command]:
    found = []
    for page in PAGES:
        for command in shell_lines(page):
            tokens = words(command.text)
            if fedlgr_argv(tokens) is not None or (not tokens and "fedlgr" in command.text):
                found.append(command)
    return found


def is_placeholder(token: str) -> bool:
    """``$VAR``, ``<x>``, ``...``, ``key=value``, or a word in capitals (``CONFIG``, ``RUN_ID``)."""
    return (
        "$" in token
        or "<" in token
        or "..." in token
        or token.lower() == "key=value"
        or bool(re.fullmatch(r"[A-Z][A-Z0-9_]*", token))
    )


def unbracket(argv: list[str]) -> list[str]:
    """``[--size 128]`` -> ``--size 128``; a bare ``...`` goes."""
    out = []
    for token in argv:
        token = token.lstrip("[").rstrip("]")
        if token and token != "...":
            out.append(token)
    return out


def parsed(argv: list[str], where: str):
    """fedlgr's own parse of ``argv``; None for ``--help`` / ``--version``; a usage error fails
    with argparse's message."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            return parse(argv)
    except SystemExit as stop:
        code = stop.code
    if code != 0:
        usage = err.getvalue().strip().splitlines()
        pytest.fail(f"{where}: fedlgr {shlex.join(argv)}\n  {usage[-1]}", pytrace=False)
    return None


def concrete(overrides: list[str]) -> list[str]:
    """The overrides to load: those without a placeholder; a placeholder ``data.path``
    (``data.path=...``) becomes a path, as the MANNERS-DB presets need one."""
    kept = []
    for item in overrides:
        key, _, value = item.partition("=")
        if item.lower() == "key=value" or is_placeholder(key):
            continue
        if not is_placeholder(value):
            kept.append(item)
        elif key == "data.path":
            kept.append("data.path=/path/to/manners-db")
    return kept


def check_config(config: str | None, overrides: list[str]) -> None:
    """``config`` (a file, or a name in conf/) with the overrides that are not placeholders
    loads as ``fedlgr run`` loads it; a placeholder config checks the overrides alone."""
    path = None
    if config is not None and not is_placeholder(config):
        path = find_config(config)
        if not path.is_file():
            raise FedlgrError(f"config {config}: no such file (nor in conf/)")
    load_config(path, concrete(overrides))


def check_sweep(name: str, overrides: list[str]) -> None:
    """The sweep file exists and its base config loads with the overrides (the trials' own
    points are ``fedlgr sweep``'s check, which imports torch: too slow here)."""
    from fedlgr.shell.sweep.spec import find_sweep, read_sweep_file, resolve_config

    if is_placeholder(name):
        load_config(None, concrete(overrides))
        return
    path = find_sweep(name)
    raw = read_sweep_file(path)
    base = resolve_config(raw["base"], path) if raw.get("base") else None
    load_config(base, [*(raw.get("overrides") or []), *concrete(overrides)])


def check_command(argv: list[str], where: str) -> None:
    args = parsed(unbracket(argv), where)
    if args is None:
        return
    if args.verb == "run":
        config, overrides = split_config_and_overrides(args.items)
        check_config(config, overrides)
    elif args.verb == "deploy" and hasattr(args, "config") and hasattr(args, "overrides"):
        check_config(args.config, args.overrides)
    elif args.verb == "sweep":
        check_sweep(args.sweep, args.overrides)
    elif args.verb == "demo" and args.overrides:
        check_config("experiment/demo.yaml", args.overrides)
    elif args.verb == "report" and args.where:
        load_config(None, concrete(args.where))


COMMANDS = fedlgr_commands()


def test_docs_have_fedlgr_commands():
    """The collection itself works: the README and most pages hold commands to check."""
    pages = {c.page for c in COMMANDS}
    assert "README.md" in pages and len(pages) >= 6, pages
    assert len(COMMANDS) >= 30, len(COMMANDS)


@pytest.mark.parametrize("command", COMMANDS, ids=[c.id for c in COMMANDS])
def test_fedlgr_command_parses(command: Command):
    """The command parses with ``fedlgr``'s parser and its config and overrides load."""
    skip = next((reason for piece, reason in CONFIG_SKIPS.items() if piece in command.text), None)
    for tokens in expansions(command):
        argv = fedlgr_argv(tokens)
        if skip:
            parsed(unbracket(argv), command.id)
            continue
        problem = None
        try:
            check_command(argv, command.id)
        except FedlgrError as err:
            problem = f"{command.id}: {command.text}\n  {err}"
        if problem:
            pytest.fail(problem, pytrace=False)
    if skip:
        pytest.skip(f"{command.id}: config not loaded: {skip}")


def test_config_skips_are_few_and_used():
    assert len(CONFIG_SKIPS) <= 3
    for piece in CONFIG_SKIPS:
        assert any(piece in c.text for c in COMMANDS), f"stale CONFIG_SKIPS entry {piece!r}"


SCRIPTS = [
    (command, token)
    for page in PAGES
    for command in shell_lines(page)
    for tokens in [words(command.text)]
    if tokens[:3] == ["uv", "run", "python"] and len(tokens) > 3
    for token in [tokens[3]]
    if token.endswith(".py")
]


@pytest.mark.parametrize(
    ("command", "script"), SCRIPTS, ids=[f"{c.id}:{s}" for c, s in SCRIPTS] or None
)
def test_python_scripts_exist(command: Command, script: str):
    assert (ROOT / script).is_file(), f"{command.id}: {script}: no such file"


def test_readme_is_short():
    lines = len(README.read_text(encoding="utf-8").splitlines())
    assert lines < README_MAX_LINES, f"README.md has {lines} lines; move detail to docs/"


LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    found = set()
    for _, line in prose_lines(path.read_text(encoding="utf-8")):
        heading = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if heading:
            base = slug(heading.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            found.add(base if n == 0 else f"{base}-{n}")
    return found


def relative_links(path: Path):
    for number, line in prose_lines(path.read_text(encoding="utf-8")):
        for target in LINK.findall(line):
            if not re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
                yield number, target


LINKS = [(page, number, target) for page in PAGES for number, target in relative_links(page)]


@pytest.mark.parametrize(
    ("page", "number", "target"), LINKS, ids=[f"{rel(p)}:{n}" for p, n, _ in LINKS]
)
def test_relative_link_resolves(page: Path, number: int, target: str):
    file, _, anchor = target.partition("#")
    where = f"{rel(page)}:{number}: {target}"
    resolved = (page.parent / file).resolve() if file else page
    assert resolved.exists(), f"{where}: no such file"
    if anchor and resolved.suffix == ".md":
        assert anchor in anchors(resolved), f"{where}: no heading with anchor #{anchor}"


def test_readme_links_every_docs_page():
    linked = {
        (README.parent / target.partition("#")[0]).resolve()
        for _, target in relative_links(README)
        if target.startswith("docs/") and target.partition("#")[0].endswith(".md")
    }
    for page in linked:
        assert page.is_file(), f"README.md links {rel(page)}, which does not exist"
    missing = [rel(p) for p in DOC_PAGES if p.resolve() not in linked]
    assert not missing, f"README.md's Documentation list leaves out {missing}"


@pytest.mark.parametrize("page", DOC_PAGES, ids=[rel(p) for p in DOC_PAGES])
def test_page_starts_with_a_summary(page: Path):
    """A title, then a summary of one to three lines before the first section."""
    lines = page.read_text(encoding="utf-8").splitlines()
    assert lines[0].startswith("# "), f"{rel(page)}:1: expected a '# Title'"
    assert lines[1] == "", f"{rel(page)}:2: expected a blank line after the title"
    summary = []
    for line in lines[2:]:
        if not line.strip():
            break
        summary.append(line)
    assert 1 <= len(summary) <= 3 and not summary[0].startswith(("#", "```", "|", "-")), (
        f"{rel(page)}:3: expected a 1-3 line summary of the page"
    )
