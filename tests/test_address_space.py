"""``fedlgr run`` under an address-space limit (``ulimit -v``, set with setrlimit in the
real child process): issue 37's tester (Deliver 7) saw 17-95-line tracebacks at 1-7 GB -
torch's shared objects that could not be mapped, and allocations that failed - and a
limit of 3 GB here aborts the process while torch loads (C++ ``std::bad_alloc``). Each is
one line naming the limit and how to raise it."""

from __future__ import annotations

import re
import resource
import subprocess
import sys

import pytest

from fedlgr.shell.checks.address_space import out_of_address_space
from tests.support.processes import child_env, run_args

ONE_LINE = re.compile(
    r"fedlgr: error: the address-space limit \(ulimit -v\) of (\d+\.\d\d) GB is too small "
    r"for fedlgr run: (.+); raise it \(ulimit -v unlimited in a new shell: this one cannot "
    r"go above \1 GB\)"
)


def _limited(gb: float, command: list[str], cwd) -> subprocess.CompletedProcess:
    """``command`` in a child whose soft and hard RLIMIT_AS are ``gb`` (as ``ulimit -v``
    sets them)."""
    limit = int(gb * 1e9)
    return subprocess.run(
        command,
        cwd=cwd,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (limit, limit)),
    )


def _the_one_line(done: subprocess.CompletedProcess, gb: float) -> str:
    """The child's only output: one error line naming the limit; its reason."""
    output = (done.stdout + done.stderr).strip()
    assert done.returncode == 1 and "Traceback" not in output, output[-3000:]
    assert done.stdout == "" and len(done.stderr.strip().splitlines()) == 1, output[-3000:]
    found = ONE_LINE.fullmatch(done.stderr.strip())
    assert found is not None and found.group(1) == f"{gb:.2f}", done.stderr
    return found.group(2)


@pytest.mark.parametrize("gb", [1.0, 3.0], ids=["map-segment", "bad-alloc-abort"])
def test_a_limit_too_small_to_load_torch_is_one_line_before_it_loads(
    gb, synth_dir, cache_dir, tmp_path
):
    """1 GB: libtorch's shared objects could not be mapped (an ImportError's traceback);
    3 GB: they were, and a static initialiser's allocation then failed (``terminate called
    after throwing an instance of 'std::bad_alloc'``, SIGABRT). Both are refused as torch's
    import starts, with what did not fit."""
    args = run_args(synth_dir, cache_dir, f"sqlite:///{tmp_path}/mlflow.db")
    done = _limited(gb, [sys.executable, "-m", "fedlgr", "run", *args], tmp_path)
    why = _the_one_line(done, gb)
    assert re.fullmatch(
        r"this process \(\d+\.\d\d GB\) and torch's shared objects with the CUDA libraries "
        r"installed beside it \(\d+\.\d\d GB\) take more",
        why,
    ), why
    assert not (tmp_path / "mlflow.db").exists()  # refused before anything was made


@pytest.mark.slow
def test_an_allocation_past_the_limit_is_one_line(synth_dir, cache_dir, tmp_path):
    """6 GB holds torch, Lightning and MLflow (about 4.2 GB here), not a top whose first
    Linear weight alone is 3.07 GB (1280 x 600,000 float32): torch's CPU allocator fails
    (a RuntimeError's traceback before) and the line says what it could not allocate."""
    args = run_args(
        synth_dir, cache_dir, f"sqlite:///{tmp_path}/mlflow.db", "model.top_hidden=600000"
    )
    done = _limited(6.0, [sys.executable, "-m", "fedlgr", "run", *args], tmp_path)
    why = _the_one_line(done, 6.0)
    assert "can't allocate memory: you tried to allocate 3072000000 bytes" in why, why


IMPORT_TORCH = """
import resource, sys
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
from fedlgr.shell.checks.address_space import out_of_address_space
try:
    import torch
except ImportError as err:
    print(type(err).__name__, out_of_address_space(err, "run"))
"""


def test_torch_that_cannot_be_mapped_is_said_in_one_line(tmp_path):
    """Where the limit is not checked before torch loads (torch's libraries elsewhere than
    its wheels), the ImportError of its import is said as the limit's line too."""
    limit = int(1e9)
    done = subprocess.run(
        [sys.executable, "-c", IMPORT_TORCH, str(limit)],
        cwd=tmp_path,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    kind, line = done.stdout.strip().split(" ", 1)
    assert kind == "ImportError"
    assert line.startswith(
        "the address-space limit (ulimit -v) of 1.00 GB is too small for fedlgr run: "
    )
    assert "failed to map segment from shared object; raise it (" in line, line


def test_without_a_limit_no_error_is_the_limit_s():
    """Without a limit (this process's), an error is nobody's limit's fault."""
    if resource.getrlimit(resource.RLIMIT_AS)[0] != resource.RLIM_INFINITY:
        pytest.skip("the tests run under an address-space limit")
    assert out_of_address_space(MemoryError(), "run") is None
