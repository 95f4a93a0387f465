"""Every benchmark script's smoke run (slow tier), so that none breaks unseen: each runs in a
process of its own with its smallest arguments or ``--quick``, from the repository's root,
its caches, MLflow stores, outputs and temporary files in the test's folder. A run passes
when it exits without a traceback, with status 0, or 1 where a target was MISSED (timing
targets are met on a quiet machine, not on a busy test runner), and prints its figures.

The test that covers each script (one each; bench/README.md describes the scripts):

- ``checkpoint.py``: ``test_checkpoint``
- ``data.py``: ``test_data``
- ``evaluate.py``: ``test_evaluate``
- ``ewc.py``: ``tests/test_continual.py::test_the_ewc_benchmark_prints_its_three_tables``
- ``fcl.py``: ``test_fcl``
- ``figures.py``: ``test_checkpoint`` (a module the scripts print their figures with; its
  lines are read there, and in ``test_data``, ``test_evaluate`` and ``test_train``)
- ``flops.py``: ``tests/test_flops.py::test_the_benchmark_runs_a_round_below_the_peak``
- ``flower.py``: ``test_flower``
- ``gpu.py``: ``test_gpu`` (``--help`` alone: its parts need a CUDA GPU)
- ``paper_cpu.py``: ``test_paper_cpu``
- ``privacy.py``: ``tests/test_privacy_bench.py`` (its ``--quick`` run)
- ``privacy_attack.py``: ``tests/test_privacy_bench.py`` (a module ``privacy.py`` runs)
- ``robust.py``: ``test_robust``
- ``scale.py``: ``test_scale``
- ``scale_case.py``: ``tests/test_scale_bench.py::test_one_case_runs_in_a_process_of_its_own``
- ``secagg.py``: ``test_secagg``
- ``train.py``: ``test_train``
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.checkout import REPO
from tests.support.report import printed_rows

BENCH = REPO / "bench"
PNG = b"\x89PNG\r\n\x1a\n"


def run(script: str, tmp_path: Path, *args: str, timeout: float = 300) -> str:
    """``bench/<script> args`` from the repository's root; its standard output."""
    (tmp_path / "tmp").mkdir(exist_ok=True)
    env = {
        **os.environ,
        "FEDLGR_CACHE_DIR": str(tmp_path / "cache"),
        "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}",
        "TMPDIR": str(tmp_path / "tmp"),  # the scripts' working folders, removed with it
    }
    done = subprocess.run(
        [sys.executable, str(BENCH / script), *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    said = done.stdout[-3000:] + "\n" + done.stderr[-3000:]
    assert "Traceback" not in done.stdout + done.stderr, said
    # 1: a target MISSED (figures.report), after every figure was printed
    assert done.returncode == 0 or (done.returncode == 1 and "MISSED" in done.stdout), said
    return done.stdout


def figures(stdout: str) -> dict[str, float]:
    """The figures ``bench/figures.py`` printed, one a line: ``  name  value  (target)``."""
    found = {}
    for line in stdout.splitlines():
        match = re.fullmatch(r"  (\S+) +(-?[\d.]+|inf|nan)(  \(.*\))?", line)
        if match:
            found[match.group(1)] = float(match.group(2))
    return found


@pytest.mark.slow
def test_every_script_is_covered_once():
    """The list above names every script in bench/, once."""
    listed = re.findall(r"^- ``(\w+\.py)``:", __doc__, flags=re.MULTILINE)
    assert listed == sorted(p.name for p in BENCH.glob("*.py"))


@pytest.mark.slow
def test_checkpoint(tmp_path):
    """The demo's round and its checkpoint, then full-width checkpoints of 2 and 10 clients
    (~20 s): ten clients' optimiser states make a larger file than two."""
    out = run("checkpoint.py", tmp_path, "--scenes", "60", "--repeats", "1")
    assert out.startswith("fedlgr checkpoint benchmark")
    found = figures(out)
    names = ["demo_round_s", "demo_checkpoint_s", "demo_checkpoint_mb", "demo_checkpoint_share_%"]
    names += [f"full_{n}c_checkpoint_{u}" for n in (2, 10) for u in ("s", "mb")]
    assert list(found) == names and all(v > 0 for v in found.values()), found
    assert found["full_10c_checkpoint_mb"] > found["full_2c_checkpoint_mb"] > 0
    assert "(<= 5: " in out  # the demo's share, against its target


@pytest.mark.slow
def test_data(tmp_path):
    """Synthesis, cold and warm loads, the augmented pipeline and ``fedlgr --help`` (~10 s)."""
    out = run("data.py", tmp_path, "--scenes", "40", "--size", "32", "--epochs", "1")
    assert "40 scenes at 32 px; augmented pipeline: batch 16, 10 copies per scene" in out
    assert "1 epochs = 400 images" in out  # 40 scenes x 10 copies
    found = figures(out)
    names = ["synthesis_s", "cold_load_s", "warm_load_s", "augmented_img_per_s", "help_s"]
    assert list(found) == names and all(v > 0 for v in found.values()), found


@pytest.mark.slow
def test_evaluate(tmp_path):
    """Whole models against one shared root pass, their outputs identical (~10 s)."""
    out = run(
        "evaluate.py",
        tmp_path,
        *("--scenes", "40", "--size", "32", "--clients", "2"),
        "--repeats",
        "1",
    )
    assert "FedRootAvg, 2 clients, 10 test scenes at 32 px" in out and "outputs identical" in out
    found = figures(out)
    assert list(found) == ["eval_s_before", "eval_s_after", "eval_ratio"], found
    assert all(v > 0 for v in found.values()), found


@pytest.mark.slow
def test_train(tmp_path):
    """Every side-by-side figure, the references' and the evaluation's (~40 s)."""
    out = run(
        "train.py", tmp_path, *("--scenes", "48", "--size", "32", "--epochs", "1"), "--repeats", "1"
    )
    assert out.startswith("fedlgr training benchmark")
    found = figures(out)
    for name in (
        "concurrent_speedup",
        "concurrent_vs_procs",
        "sequential_vs_plain",
        "speedup_10_clients",
        "plain_procs_img_per_s",
        "plain_threads_img_per_s",
        "seq10_img_per_s",
        "conc10_img_per_s",
        "eval_ratio",
    ):
        assert found.get(name, 0) > 0, (name, found)


@pytest.mark.slow
def test_paper_cpu(tmp_path):
    """Both methods measured both ways, the server evaluating FedAvg alone (~10 s)."""
    out = run("paper_cpu.py", tmp_path, "--rounds", "1", "--scenes", "40", "--size", "32")
    methods = ("FedAvg", "FedRootAvg")
    table = {w[0]: w[1:] for w in map(str.split, out.splitlines()) if w and w[0] in methods}
    assert [(m, r[0]) for m, r in table.items()] == [("FedAvg", "yes"), ("FedRootAvg", "no")]
    assert all(float(v) > 0 for r in table.values() for v in r[1:]), table
    assert "FedRootAvg's reduction against FedAvg: paper-style " in out


@pytest.mark.slow
def test_fcl(tmp_path):
    """FedRoot-FT and FedLGR on the descriptors, a round per task, the VAE fits cut to 2
    epochs (~40 s): the forgetting table, Table IV and the checks, every run saved."""
    work = tmp_path / "work"
    out = run(
        "fcl.py",
        tmp_path,
        *("--modality", "features", "--seeds", "0", "--methods", "--seeded", "FedRoot-FT"),
        *("--lgr", "FedLGR", "--no-oracles", "--rounds-per-task", "1", "--epochs", "1"),
        *("--size", "32", "--set", "continual.lgr.epochs=2", "--workdir", str(work)),
    )
    assert "== features: synthetic data, 1000 scenes, 2 clients, circle then arrow" in out
    for label in ("FedRoot-FT seed 0", "FedLGR seed 0"):
        assert re.search(rf"^{label} +\d", out, flags=re.MULTILINE), label
    assert "## Table IV" in out and "checks (FedLGR at its defaults):" in out
    saved = json.loads((work / "fcl_results_features.json").read_text())
    assert list(saved) == ["features FedRoot-FT seed 0", "features FedLGR seed 0"]


@pytest.mark.slow
def test_robust(tmp_path):
    """Every strategy in both scopes without attackers, and drop-out, one round (~30 s):
    the tables, robust.json and robust.png."""
    out_dir = tmp_path / "out"
    out = run(
        "robust.py",
        tmp_path,
        *("--seeds", "0", "--clients", "4", "--rounds", "1", "--byzantine", "0"),
        *("--dropout", "0", "0.5", "--out", str(out_dir), "--workdir", str(tmp_path / "work")),
    )
    assert "== features: final test RMSE / PCC / server CPU s per round" in out
    for name in ("FedAvg", "FedMedian", "FedTrimmedAvg", "Krum", "FedRootKrum", "FedRootAvg"):
        assert re.search(rf"^{name} +\d", out, flags=re.MULTILINE), name
    cells = json.loads((out_dir / "robust.json").read_text())["features"]
    assert len(cells) == 2 * 4 + 2  # scopes x strategies, and FedAvg / FedRootAvg drop-out
    assert (out_dir / "robust.png").read_bytes()[:8] == PNG


@pytest.mark.slow
def test_scale(tmp_path):
    """One case of ``--quick``'s grid, FedAvg with 4 clients, in its own process (~45 s):
    its row, results.json and the plot."""
    work, out_dir = tmp_path / "work", tmp_path / "out"
    out = run(
        "scale.py",
        tmp_path,
        *("--quick", "--cases", "avg-4", "--threads", "1"),
        *("--work", str(work), "--out", str(out_dir)),
    )
    [row] = printed_rows(out, "| case | method |")
    assert row[:6] == ["avg-4", "FedAvg", "image", "4", "1", "issue 40"]
    assert all(float(cell) > 0 for cell in row[6:-1]), row  # every figure, no note
    [case] = json.loads((work / "results.json").read_text())
    assert case["status"] == "ok" and len(case["wall_s"]) == 2  # --quick: 2 rounds
    assert (out_dir / "scale.png").read_bytes()[:8] == PNG


@pytest.mark.slow
def test_flower(tmp_path):
    """``--quick``: a real federation of this checkout on localhost, one round, then a typo
    reported in one line (~1.5 min)."""
    out = run("flower.py", tmp_path, "--quick", timeout=600)
    [row] = printed_rows(out, "| code | wall |")
    assert row[0] == "now" and float(row[1]) > 0, row
    assert re.fullmatch(r"\d+ x [\d.]+", row[3]), row  # the exchanges
    typo = next(line for line in out.splitlines() if line.startswith("config typo reported"))
    assert "(exit 1)" in typo and "federated.roundz" in typo, typo


@pytest.mark.slow
def test_secagg(tmp_path):
    """``--quick``: SecAgg+ on two robots of a real federation, one round (~1.5 min): the
    key stages' bytes and the masked vector's are there."""
    out = run("secagg.py", tmp_path, "--quick", timeout=600)
    [row] = printed_rows(out, "| setting |")
    assert row[0] == "SecAgg+", row
    head = ["round s", "bytes up", "key stages up", "bytes down", "key stages down"]
    for name, cell in zip(head, row[1:6], strict=True):
        assert float(cell.removesuffix(" KB")) > 0, (name, row)


@pytest.mark.slow
def test_gpu(tmp_path):
    """Its parts need a CUDA GPU (``tests/test_gpu.py``'s marker runs them there): here its
    help, which imports what it imports from bench/train.py."""
    out = run("gpu.py", tmp_path, "--help")
    assert "The GPU checks in one call" in out and "--json" in out
