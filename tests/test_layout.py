"""The package's boundaries, read from the source: the two sides of a federation meet only
through the messages, and the method registry and the config stay free of torch. The
tests' own: no test module imports another or conftest (shared code is in tests/support)."""

from __future__ import annotations

import ast
import io
import re
import subprocess
import sys
import tokenize
from pathlib import Path

import pytest

import fedlgr

PACKAGE = Path(fedlgr.__file__).parent
CORE = PACKAGE / "core"


def imported_modules(source: str, module: str) -> set[str]:
    """Every module ``source`` (the text of ``module``) imports, anywhere in it (imports
    inside functions too), relative imports resolved."""
    out = set()
    package = module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{alias.name}" for alias in node.names)
    return out


def side_crossings(side: str, other: str) -> list[str]:
    """``module -> imported`` for every module under ``core/<side>/`` that imports one
    under ``core/<other>/``."""
    crossings = []
    for path in sorted((CORE / side).rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        for name in imported_modules(path.read_text(), module):
            if name == f"fedlgr.core.{other}" or name.startswith(f"fedlgr.core.{other}."):
                crossings.append(f"{module} -> {name}")
    return crossings


@pytest.mark.parametrize(("side", "other"), [("client", "server"), ("server", "client")])
def test_client_and_server_modules_never_import_each_other(side, other):
    assert list((CORE / side).glob("*.py")), f"core/{side}/ has no modules"
    assert side_crossings(side, other) == []


def test_the_import_reader_sees_every_form_of_import():
    source = (
        "import fedlgr.core.server.side\n"
        "from fedlgr.core.server import aggregate\n"
        "def later():\n"
        "    from ..server.side import ServerSide\n"
    )
    found = imported_modules(source, "fedlgr.core.client.side")
    assert "fedlgr.core.server.side" in found
    assert "fedlgr.core.server.aggregate" in found
    assert "fedlgr.core.server.side.ServerSide" in found


def test_the_registry_and_the_config_load_without_torch():
    """A config is checked, and every method's settings and names are known, before torch
    is imported (the CLI answers --help and --print-config in a second)."""
    code = (
        "import sys, fedlgr.core.methods, fedlgr.shell.config\n"
        "fedlgr.shell.config.load_config(None, ['method=FedRoot-EWC', 'continual.ewc.lambda_=2'])\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'torchvision')))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]", done.stdout


def test_every_registered_method_loads_its_class():
    from fedlgr.core.client.plugins import ClientPlugin
    from fedlgr.core.methods import CONTINUAL, STRATEGIES
    from fedlgr.core.strategies.base import Strategy

    for method in STRATEGIES.values():
        assert issubclass(method.load(), Strategy), method.key
    for method in CONTINUAL.values():
        if method.target is not None:
            assert issubclass(method.load(), ClientPlugin), method.key


# --------------------------------------------------------------------------- the layers

ROOT = PACKAGE.parent


@pytest.mark.slow  # also a step of .ci/run
def test_the_import_contracts_hold():
    """The layers of pyproject.toml's [tool.importlinter]: the shell calls the core, the
    core never imports the shell (nor MLflow, Optuna, Flower); a robot's side and the
    server's never import each other; sweeps, reports and robots stay apart."""
    done = subprocess.run(
        [str(Path(sys.executable).with_name("lint-imports")), "--no-cache"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stdout[-3000:]
    assert "5 kept, 0 broken" in done.stdout, done.stdout[-3000:]


def import_graph():
    """fedlgr's modules and what each imports: every import grimp finds - inside
    functions too - but those under ``if TYPE_CHECKING:``, which never run."""
    import grimp
    import networkx as nx

    graph = grimp.build_graph("fedlgr", exclude_type_checking_imports=True, cache_dir=None)
    edges = [
        (module, imported)
        for module in graph.modules
        for imported in graph.find_modules_directly_imported_by(module)
        if imported.startswith("fedlgr")
    ]
    return nx.DiGraph(edges)


@pytest.mark.slow  # grimp reads the whole package
def test_no_import_cycle_among_fedlgr_s_modules():
    """A cycle means a piece sits in the wrong module (or layer)."""
    import networkx as nx

    graph = import_graph()
    assert graph.number_of_edges() > 300  # the whole package was read
    cycles = [sorted(c) for c in nx.strongly_connected_components(graph) if len(c) > 1]
    assert cycles == []


def functions(path: Path):
    """Every function (and method) of a module: ``(name, first line, lines)``."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            yield node.name, node.lineno, node.end_lineno - node.lineno + 1


MAX_FUNCTION_LINES = 80


def test_no_function_is_over_80_lines():
    """A function longer than a screen is a sequence of steps that want names."""
    long = [
        f"{path.relative_to(ROOT)}:{line} {name} ({n} lines)"
        for path in sorted(PACKAGE.rglob("*.py"))
        for name, line, n in functions(path)
        if n > MAX_FUNCTION_LINES
    ]
    assert long == []


def imports_inside_functions(path: Path) -> list[tuple[int, bool]]:
    """``(line, says why)`` for each import inside a function (not under TYPE_CHECKING):
    it says why with a ``# lazy:`` comment on its line or above its block of imports."""
    lines = path.read_text(encoding="utf-8").splitlines()
    found = []

    def visit(node, inside: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue
            if inside and isinstance(child, ast.Import | ast.ImportFrom):
                found.append((child.lineno, _says_why(lines, child.lineno, child.end_lineno)))
            visit(child, inside or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef))

    visit(ast.parse("\n".join(lines)), False)
    return found


def _says_why(lines: list[str], first: int, last: int) -> bool:
    if any("# lazy:" in lines[i - 1] for i in range(first, last + 1)):
        return True
    k = first - 2  # the lines above, while they are imports of the same block or comments
    while k >= 0:
        text = lines[k].strip()
        if text.startswith("# lazy:"):
            return True
        if not (text.startswith(("import ", "from ", "#", ")")) or text.endswith(",")):
            return False
        k -= 1
    return False


def test_an_import_inside_a_function_says_why():
    """Imports sit at the top of a module; one inside a function keeps ``fedlgr --help``
    or a torch-free module fast, and says so (``# lazy: <why>``)."""
    unexplained = [
        f"{path.relative_to(ROOT)}:{line}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for line, why in imports_inside_functions(path)
        if not why
    ]
    assert unexplained == []


def test_the_import_checks_read_what_they_must():
    source = (
        "def f():\n"
        "    # lazy: torch\n"
        "    import torch\n"
        "    from torch import nn\n"
        "def g():\n"
        "    import numpy\n"
        "    x = 1\n"
        "    import yaml  # lazy: yaml\n"
    )
    path = TESTS / "__pycache__" / "layout_probe.py"
    path.parent.mkdir(exist_ok=True)
    path.write_text(source)
    try:
        assert imports_inside_functions(path) == [(3, True), (4, True), (6, False), (8, True)]
        assert [(name, n) for name, _, n in functions(path)] == [("f", 4), ("g", 4)]
    finally:
        path.unlink()


# Words and case ids of fault-finding campaigns: "the ninth fault sweep", "(c113, c114)",
# "d24-d74", "g03e". A comment says why in a plain sentence; the case lives in its test.
ORDINALS = "first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth"
CAMPAIGN = re.compile(rf"\bfault[ -]sweeps?\b|\b(?:{ORDINALS}) sweep\b", re.I)
CASE_IDS = re.compile(
    r"\((?:[a-z]{1,2}\d{2,3}[a-z]?)(?:\s*(?:[,;-]|and)\s*[a-z]{0,2}\d{2,3}[a-z]?)*\)"
)


def prose(path: Path) -> list[tuple[int, str]]:
    """The comments and docstrings of a module, by line."""
    source = path.read_text(encoding="utf-8")
    out = [
        (token.start[0], token.string)
        for token in tokenize.generate_tokens(io.StringIO(source).readline)
        if token.type == tokenize.COMMENT
    ]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            doc = ast.get_docstring(node, clean=False)
            if doc:
                out.append((node.body[0].lineno, doc))
    return out


def test_no_comment_cites_a_fault_finding_campaign():
    cited = [
        f"{path.relative_to(ROOT)}:{line}: {text.strip()[:80]}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for line, text in prose(path)
        if CAMPAIGN.search(text) or CASE_IDS.search(text)
    ]
    assert cited == []


def test_the_campaign_patterns_find_what_they_must():
    for text in ("(the ninth fault sweep, c06)", "the tenth sweep", "(c113, c114)", "(d24-d74)"):
        assert CAMPAIGN.search(text) or CASE_IDS.search(text), text
    for text in ("(2 clients)", "float64 (8,)", "(PCC 0.53)", "a 128 px image", "(x4)"):
        assert not (CAMPAIGN.search(text) or CASE_IDS.search(text)), text


# Citations of documents a reader of the code does not have: the "SPEC" the first version
# was written from ("SPEC 4.2") and the project's issues ("issue 48", "(#19)"). A comment
# says the fact or points at docs/. Another project's pull request ("pytorch/pytorch PR
# #183405") is a citation a reader can follow.
SPEC = re.compile(r"\bSPEC\b")
ISSUE = re.compile(r"\bissues?\s*#?\d+|(?<!PR )(?<![\w/&])#\d+\b", re.I)


def citations(path: Path) -> list[str]:
    """``file:line: text`` for every comment or docstring of ``path`` that cites the SPEC or
    an issue number."""
    return [
        f"{path.relative_to(ROOT).as_posix()}:{line}: {text.strip()[:80]}"
        for line, text in prose(path)
        if SPEC.search(text) or ISSUE.search(text)
    ]


def test_no_comment_cites_the_spec_or_an_issue_number():
    cited = [hit for path in sorted(PACKAGE.rglob("*.py")) for hit in citations(path)]
    assert cited == []


def test_the_citation_patterns_find_what_they_must():
    cites = ("(SPEC 4.2)", "the SPEC", "issue 48", "before Issue 9", "(#19)", "issues 19")
    for text in cites:
        assert SPEC.search(text) or ISSUE.search(text), text
    plain = ("SweepSpec", "spec.path", "pytorch/pytorch PR #183405", "owner/repo#12", "tissue 3")
    for text in plain:
        assert not (SPEC.search(text) or ISSUE.search(text)), text


# --------------------------------------------------------------------------- the tests' own

TESTS = Path(__file__).resolve().parent


def names_a_test_module(name: str) -> bool:
    """``name`` (an imported module or name) is a conftest, a test module or in one."""
    parts = name.split(".")
    inside = parts[1:] if parts[0] == "tests" else parts[:1]
    return any(p == "conftest" or p.startswith("test_") for p in inside)


def forbidden_imports(path: Path) -> list[str]:
    """What ``path`` (a file under tests/) imports from conftest or a test module."""
    module = ".".join(path.relative_to(TESTS.parent).with_suffix("").parts)
    found = imported_modules(path.read_text(encoding="utf-8"), module)
    return sorted(name for name in found if names_a_test_module(name))


def test_no_test_module_imports_another_or_conftest():
    """What tests share is in tests/support (fixtures in conftest.py, found by pytest): a
    test module, conftest and tests/support import fedlgr, libraries and tests/support,
    never conftest or a test module."""
    checked = sorted(p for p in TESTS.rglob("*.py") if "__pycache__" not in p.parts)
    assert TESTS / "conftest.py" in checked and TESTS / "support" / "runs.py" in checked
    found = {
        path.relative_to(TESTS).as_posix(): names
        for path in checked
        if (names := forbidden_imports(path))
    }
    assert found == {}


def test_the_test_import_reader_sees_conftest_and_test_modules_in_every_form():
    source = (
        "from tests.conftest import FAST\n"
        "from .conftest import fast_config\n"
        "import tests.test_lgr\n"
        "from . import test_report\n"
        "def later():\n"
        "    from tests.test_batched import Float64Batches\n"
        "    from .test_sweep import child_runs\n"
        "from tests.support.runs import results_csv\n"
        "from .support import lgr\n"
        "import testing_tools\n"
    )
    found = {n for n in imported_modules(source, "tests.test_x") if names_a_test_module(n)}
    assert {
        "tests.conftest",
        "tests.test_lgr",
        "tests.test_report",
        "tests.test_batched",
        "tests.test_sweep",
    } <= found
    assert not any(n.startswith(("tests.support", "testing_tools")) for n in found)
