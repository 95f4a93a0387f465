"""The package's boundaries, read from the source: the two sides of a federation meet only
through the messages, and the method registry and the config stay free of torch. The
tests' own: no test module imports another or conftest (shared code is in tests/support)."""

from __future__ import annotations

import ast
import subprocess
import sys
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
