"""``bench/privacy.py --quick``: both tables in their format, with sane values, and the plot
(issue 38). One run of seed 0 (~40 s on 2 cores); what is asserted holds for it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from fedlgr.core.privacy import epsilon
from tests.support.checkout import REPO
from tests.support.report import printed_rows

ATTACK_HEAD = "| shared | the server sees | epsilon (one round) | loss_diff AUC | grad_cos AUC |"
UTILITY_HEAD = "| method | noise multiplier | clip | epsilon (all rounds) | RMSE | PCC | CCC |"
QUICK_NOISE = [1.0, 4.0]  # bench/privacy.py's --quick noise multipliers
ATTACK_NOISE = [0.0, 0.01, 0.3, 1.0]  # and its attack's
QUICK_RATE, QUICK_ROUNDS = 0.5, 3  # and its utility runs' fraction and rounds


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("privacy")
    done = subprocess.run(
        [sys.executable, str(REPO / "bench" / "privacy.py"), "--quick", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=out,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout, out


def table(stdout: str, head: str) -> list[list[str]]:
    """The rows (cells) of the table whose whole header line is ``head``."""
    assert head in stdout.splitlines()
    return printed_rows(stdout, head)


def mean(cell: str) -> float:
    return float(cell.split(" ± ")[0])


# Epsilons are printed to 3 significant digits: off by at most half a unit of the third
# digit, 0.5% of a value that starts with 1.
def close(cell: str, expected: float) -> bool:
    return abs(float(cell) - expected) <= 5.01e-3 * expected


@pytest.mark.slow
def test_the_attack_table(quick):
    rows = table(quick[0], ATTACK_HEAD)
    seen = ["robot's upload", "plain aggregate", "clipped mean, no noise (z=0)"]
    seen += [f"DP release, z={z:g}" for z in ATTACK_NOISE[1:]]
    assert [(r[0], r[1]) for r in rows] == [
        (s, w) for s in ("whole model", "root only") for w in seen
    ]
    for row in rows:
        assert all(0.0 <= mean(cell) <= 1.0 for cell in row[3:]), row
    for scope in ("whole model", "root only"):
        mine = [r for r in rows if r[0] == scope]
        assert [r[2] for r in mine[:3]] == ["—", "—", "inf"]  # no DP: no epsilon
        dp = mine[3:]  # noise rising: epsilon falling, the accountant's for one release
        for row, z in zip(dp, ATTACK_NOISE[1:], strict=True):
            assert close(row[2], epsilon(z, 1.0, 1, 1e-5)), row
        assert [float(r[2]) for r in dp] == sorted((float(r[2]) for r in dp), reverse=True)
        # the robot's own upload gives it away for seed 0 (AUC 0.75-0.76 measured)
        assert mean(mine[0][3]) > 0.6, mine[0]


@pytest.mark.slow
def test_the_utility_table_and_plot(quick):
    stdout, out = quick
    rows = table(stdout, UTILITY_HEAD)
    noises = ["no DP", *(f"{z:g}" for z in QUICK_NOISE)]
    assert [(r[0], r[1]) for r in rows] == [
        (m, z) for m in ("FedAvg", "FedRootAvg") for z in noises
    ]
    for method in ("FedAvg", "FedRootAvg"):
        mine = [r for r in rows if r[0] == method]
        assert mine[0][2:4] == ["—", "—"]  # no DP: no clip, no epsilon
        for row, z in zip(mine[1:], QUICK_NOISE, strict=True):
            assert float(row[2]) > 0  # the clip norm measured on round 1
            assert close(row[3], epsilon(z, QUICK_RATE, QUICK_ROUNDS, 1e-5)), row
        assert float(mine[1][3]) > float(mine[2][3])  # less noise, more epsilon
        for row in mine:
            assert mean(row[4]) > 0 and -1 <= mean(row[5]) <= 1 and -1 <= mean(row[6]) <= 1
    png = out / "privacy-features.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
