"""``bench/scale.py`` (issue 40): its cases and their settings, the settings a checkout does
not know left out, the targets A and B read from the cases' figures, and one case run in a
process of its own (4 clients on the descriptors, ~20 s) with every figure there."""

from __future__ import annotations

import dataclasses
import importlib
import math
import sys

import pytest

from fedlgr.errors import ConfigError
from fedlgr.shell.config import load_config
from tests.support.checkout import REPO


@pytest.fixture(scope="module")
def bench():
    """``bench/scale.py`` and ``bench/scale_case.py``, imported as the scripts import each
    other (from their folder)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(REPO / "bench"))
        scale = importlib.import_module("scale")
        yield scale, importlib.import_module("scale_case")
    for name in ("scale", "scale_case", "figures"):
        sys.modules.pop(name, None)


def options(scale, **changes):
    return scale.Options(rounds=2, rounds_per_task=1, threads=1, **changes)


def test_the_cases_are_the_issue_s(bench):
    scale, _ = bench
    full = {c.name: c for c in scale.cases(scale.FULL)}
    families = ("avg", "root", "lgr-features", "lgr")
    assert list(full) == [f"{f}-{n}" for n in (10, 100, 1000) for f in families] + ["lgr-200"]
    assert [full[f"avg-{n}"].fraction for n in (10, 100, 1000)] == [1.0, 1.0, 0.01]
    b = full["lgr-200"]
    assert (b.role, b.method, b.modality, b.fraction) == ("B", "FedLGR", "image", 0.05)
    assert (full["lgr-features-10"].method, full["lgr-features-10"].modality) == (
        "FedLGR",
        "features",
    )
    assert [c.name for c in scale.select(list(full.values()), ["avg-*", "lgr-200"])] == [
        "avg-10",
        "avg-100",
        "avg-1000",
        "lgr-200",
    ]
    with pytest.raises(SystemExit, match="no such case"):
        scale.select(list(full.values()), ["nothing"])


@pytest.mark.parametrize("family", ["avg", "root", "lgr-features", "lgr"])
def test_every_case_s_settings_load(bench, family, tmp_path):
    """What a case passes is this checkout's settings: the run's store and checkpoints in
    its folder, one batch a client, a checkpoint every round."""
    scale, case_script = bench
    case = scale.Case(f"{family}-1000", family, 1000, 0.01)
    side = scale.Side(scale.NEW, REPO, sys.executable)
    job = scale.spec(case, side, tmp_path / "data", tmp_path / "run", options(scale))
    config, _ = case_script.configure(job["config"], job["overrides"], job["optional"])
    assert (config.method_name, config.data.modality) == (case.method, case.modality)
    assert (config.data.clients, config.federated.fraction) == (1000, 0.01)
    assert (config.train.max_batches, config.train.epochs, config.runtime.threads) == (1, 1, 1)
    assert config.tracking.uri == f"sqlite:///{tmp_path / 'run' / 'mlflow.db'}"
    assert config.tracking.checkpoint_dir == str(tmp_path / "run" / "checkpoints")
    assert config.continual_learning == (case.method == "FedLGR")


def test_settings_this_code_does_not_know_are_left_out(bench):
    _, case_script = bench
    preset = REPO / "conf" / "experiment" / "demo.yaml"
    optional = ["runtime.no_such_setting=1", "train.epochs=3", "federated.nor_this=x"]
    config, dropped = case_script.configure(preset, ["data.clients=3"], optional)
    assert dropped == ["runtime.no_such_setting=1", "federated.nor_this=x"]
    assert (config.train.epochs, config.data.clients) == (3, 3)
    with pytest.raises(ConfigError, match=r"train\.epochs"):  # known, but a bad value
        case_script.configure(preset, [], ["train.epochs=-1"])
    assert load_config(preset).train.epochs == 1  # the preset's own


def row(scale, name, clients, round_s, rss, status="ok", role="grid"):
    family = name.rsplit("-", 1)[0]
    case = scale.Case(name, family, clients, 1.0, role)
    return {
        "side": scale.NEW,
        **dataclasses.asdict(case),
        "method": case.method,
        "modality": case.modality,
        "status": status,
        "wall_s": [3 * round_s, round_s, round_s],
        "cpu_s": [1.0, 1.0, 1.0],
        "peak_rss_mib": rss,
    }


def test_a_and_b_are_read_from_the_cases(bench):
    """A: the most clients' peak RSS and their round against the fewest's (the median of
    the rounds after the first); B: FedLGR's RSS. A case that did not finish misses."""
    scale, _ = bench
    results = [
        row(scale, "avg-10", 10, 2.0, 1500.0),
        row(scale, "avg-1000", 1000, 2.5, 3000.0),
        row(scale, "root-10", 10, 2.0, 1500.0),
        row(scale, "root-1000", 1000, 0.0, 0.0, status="over 8 GB"),
        row(scale, "lgr-200", 200, 9.0, 5000.0, role="B"),
    ]
    figures, targets = scale.checks(results, scale.FULL)
    assert figures["avg-1000/avg-10 round"] == pytest.approx(1.25)
    assert targets["avg-1000/avg-10 round"] == (1.5, "max")
    assert figures["avg-1000 RSS MiB"] == 3000.0 and targets["avg-1000 RSS MiB"] == (4096, "max")
    assert math.isinf(figures["root-1000 RSS MiB"])
    assert math.isinf(figures["root-1000/root-10 round"])
    assert figures["lgr-200 RSS MiB"] == 5000.0
    assert scale.report(figures, targets) == 3  # root-1000 twice, lgr-200
    text = scale.table(results)
    lines = text.splitlines()
    assert lines[0].startswith("| case | method | data | clients | fraction | code | round 1 (s)")
    assert "| root-1000 | FedRootAvg | image | 1000 | 1 | issue 40 | — |" in text
    assert lines[-2].endswith("| over 8 GB |")
    assert "| avg-10 | FedAvg | image | 10 | 1 | issue 40 | 6.00 | 2.00 | 1.00 | 1500 |" in text


@pytest.mark.slow
def test_one_case_runs_in_a_process_of_its_own(bench, synth_dir, tmp_path):
    """FedAvg, 4 clients on the descriptors, 2 rounds: every figure of the case's line is
    there and positive, one per round where it is per round."""
    scale, _ = bench
    side = scale.Side(scale.NEW, REPO, sys.executable)
    case = scale.Case("avg-4", "avg", 4, 1.0)
    features = ("data.modality=features", "model.root=mlp")
    opts = options(scale, timeout=300.0, settings=features)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    job = scale.spec(case, side, synth_dir, run_dir, opts)
    figures = scale.run_case(sys.executable, job, run_dir, opts) | scale.on_disk(run_dir)
    assert figures["status"] == "ok", (run_dir / "case.err").read_text()[-3000:]
    for key in ("wall_s", "cpu_s", "round_s", "tracking_s", "checkpoint_s"):
        assert len(figures[key]) == 2 and all(v > 0 for v in figures[key]), key
    for key in ("peak_rss_mib", "polled_rss_mib", "checkpoint_mib", "setup_s", "results_s"):
        assert figures[key] > 0, key
    assert figures["total_s"] > figures["setup_s"] + sum(figures["wall_s"])
    assert figures["store_mib"] > 0 and figures["results_kib"] > 0
    assert not (run_dir / "checkpoints").exists() or not any((run_dir / "checkpoints").iterdir())
