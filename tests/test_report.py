"""fedlgr report: Tables I-IV from real fast-dev runs read back from MLflow, the marking of
best values and FedRoot reductions on hand-made numbers, sweeps, and the command line."""

from __future__ import annotations

import csv
import json
import math
import statistics
from pathlib import Path

import mlflow
import pytest

import fedlgr.shell.report.runs as report_runs
from fedlgr.core.methods import in_paper
from fedlgr.shell.cli import main
from fedlgr.shell.config import FCL_METHODS, METHODS, load_config
from fedlgr.shell.config.export import config_hash
from fedlgr.shell.report import ReportError, make_report
from fedlgr.shell.report.tables import mark_best, mark_lower_of_pair, reduction_percent
from fedlgr.shell.run.experiment import run_experiment
from fedlgr.shell.tracking.context import run_params
from fedlgr.shell.tracking.store import open_client
from tests.support.figures import drawn_figures
from tests.support.report import markdown_blocks, parse
from tests.support.runs import fast_config

EXPERIMENT = "report-test"
TABLE2 = [m for m in FCL_METHODS if not m.endswith("-FT") and in_paper(m)]
TABLE1 = [m for m in METHODS if in_paper(m)]
SCORES = ("loss", "rmse", "pcc", "ccc")
HIGHER = ("pcc", "ccc")  # higher is better


# --------------------------------------------------------------------------- marking


def test_best_is_lowest_for_errors_and_highest_for_pcc():
    assert mark_best([0.30, 0.10, 0.20], lower_is_better=True, decimals=3) == [
        "",
        "best",
        "second",
    ]
    assert mark_best([0.30, 0.10, 0.20], lower_is_better=False, decimals=3) == [
        "best",
        "",
        "second",
    ]


def test_ties_as_shown_share_a_mark_and_missing_values_get_none():
    # 0.2641 and 0.2644 both show as 0.264: both best; the next value is second.
    values = [0.2641, None, 0.2644, 0.300, math.nan, 0.500]
    assert mark_best(values, True, 3) == ["best", "", "best", "second", "", ""]
    assert mark_best(values, True, 4) == ["best", "", "second", "", "", ""]
    assert mark_best([None, 0.4], False, 3) == ["", "best"]  # a lone value is the best
    assert mark_best([None, None], True, 3) == ["", ""]


def test_cost_pairs_mark_the_lower_and_the_reduction_is_against_the_full_model():
    assert mark_lower_of_pair(19.06, 2.55, 2) == ["", "best"]
    assert mark_lower_of_pair(2.0, 3.0, 2) == ["best", ""]
    assert mark_lower_of_pair(2.001, 2.004, 2) == ["", ""]  # equal as shown
    assert mark_lower_of_pair(None, 2.0, 2) == ["", ""]
    assert reduction_percent(19.06, 2.55) == pytest.approx(86.62, abs=0.01)  # the paper's
    assert reduction_percent(0.63, 0.24) == pytest.approx(61.9, abs=0.05)
    assert reduction_percent(2.0, 3.0) == pytest.approx(-50.0)  # FedRoot costs more
    assert reduction_percent(None, 1.0) is None and reduction_percent(0.0, 1.0) is None


# --------------------------------------------------------------------------- real runs


@pytest.fixture(scope="module")
def runs(synth_dir, store, tmp_path_factory) -> dict[str, list[str]]:
    """Fast dev runs: FedAvg twice (seeds: one cell of two runs), FedRootAvg, FedAvg with
    augmentation, FedLGR through two tasks; and a FAILED FedBN run that must not count.
    Returns run ids per label."""
    client = mlflow.MlflowClient(store)
    artifacts = tmp_path_factory.mktemp("artifacts")
    client.create_experiment(EXPERIMENT, artifact_location=artifacts.as_uri())
    cache = tmp_path_factory.mktemp("cache")
    # One torch thread: far quicker than two when the machine is busy.
    common = [f"tracking.experiment={EXPERIMENT}", "runtime.threads=1"]
    plans = {
        "FedAvg": [["method=FedAvg", "seed=0"], ["method=FedAvg", "seed=1"]],
        "FedRootAvg": [["method=FedRootAvg"]],
        "FedAvg-aug": [["method=FedAvg", "data.augment=true"]],
        "FedLGR": [
            ["method=FedLGR", "continual.rounds_per_task=1", "continual.lgr.epochs=2"],
        ],
    }
    ids = {}
    for label, overrides in plans.items():
        ids[label] = [
            run_experiment(fast_config(synth_dir, cache, store, *common, *o)).run_id
            for o in overrides
        ]
    experiment_id = client.get_experiment_by_name(EXPERIMENT).experiment_id
    tags = {
        "method": "FedBN",
        "benchmark": "FL",
        "clients": "2",
        "augmentation": "false",
        "dataset": "synthetic",
        "modality": "image",
    }
    failed = client.create_run(experiment_id, run_name="FedBN-2c-noaug", tags=tags).info.run_id
    for m in SCORES:
        client.log_metric(failed, f"test/{m}", 0.0 if m != "pcc" else 1.0, step=1)
    client.set_terminated(failed, "FAILED")
    return ids


@pytest.fixture(scope="module")
def report(runs, store, tmp_path_factory):
    return make_report(store, experiment=EXPERIMENT, out=tmp_path_factory.mktemp("report"))


def metrics_of(store, run_ids: list[str]) -> dict[str, float]:
    """The mean over ``run_ids`` of each metric, as MLflow holds it."""
    client = mlflow.MlflowClient(store)
    runs = [client.get_run(r).data.metrics for r in run_ids]
    return {k: sum(r[k] for r in runs) / len(runs) for k in runs[0] if all(k in r for r in runs)}


@pytest.mark.slow
def test_table1_rows_columns_values_and_bold_best(report, runs, store):
    blocks = markdown_blocks(report.out / "table1.md")
    assert list(blocks) == ["W/O augmentation", "W/ augmentation"]
    header, rows = blocks["W/O augmentation"]
    arrows = {"loss": "Loss ▼", "rmse": "RMSE ▼", "pcc": "PCC ▲", "ccc": "CCC ▲"}
    assert header == ["Method"] + [f"{c} clients · {arrows[m]}" for c in (2, 10) for m in SCORES]
    assert list(rows) == TABLE1  # the paper's ten, in order, with or without runs
    assert len(TABLE1) == 10 and len(TABLE2) == 11

    values = {m: metrics_of(store, runs[m]) for m in ("FedAvg", "FedRootAvg")}
    for j, m in enumerate(SCORES):
        shown = {k: f"{values[k][f'test/{m}']:.3f}" for k in values}
        lower = m not in HIGHER
        best = min(shown.values(), key=float) if lower else max(shown.values(), key=float)
        for method, text in shown.items():
            assert parse(rows[method][j]) == (
                text,
                "best" if text == best else "second",
            ), (method, m)
    for method in TABLE1:
        if method not in values:  # FedBN: only a FAILED run; the others: none
            assert rows[method] == ["—"] * 2 * len(SCORES), method
        assert rows[method][len(SCORES) :] == ["—"] * len(SCORES)  # no run with ten clients

    # Two seeds in FedAvg's cell: the mean, then the standard deviation over them and n.
    client = mlflow.MlflowClient(store)
    rmse = [client.get_run(r).data.metrics["test/rmse"] for r in runs["FedAvg"]]
    assert rows["FedAvg"][1].split(" ", 1)[1] == f"(± {statistics.stdev(rmse):.3f}, n=2)"
    assert "(" not in rows["FedRootAvg"][1]  # one run: nothing to spread

    _, augmented = blocks["W/ augmentation"]
    aug = metrics_of(store, runs["FedAvg-aug"])
    assert [parse(c) for c in augmented["FedAvg"][: len(SCORES)]] == [
        (f"{aug[f'test/{m}']:.3f}", "best") for m in SCORES
    ]
    assert augmented["FedRootAvg"] == ["—"] * 2 * len(SCORES)
    text = (report.out / "table1.md").read_text(encoding="utf-8")
    assert "Built from 4 finished runs of experiment `report-test`" in text
    assert "(1 to 2 runs per value)" in text


def latex_rows(path) -> dict[tuple[str, str], list[str]]:
    """``{(block title, row label): cells}`` from a report's LaTeX file."""
    rows, title = {}, None
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith(r"\multicolumn") and line.endswith(r"\\\midrule") and " & " not in line:
            title = line.split(r"\textit{")[1].split("}")[0]
        elif title is not None and line.endswith(r"\\"):
            label, *cells = line.removesuffix(r"\\").split(" & ")
            rows[title, label.split(" $")[0].replace(r"\%", "%")] = cells
    return rows


@pytest.mark.slow
def test_csv_and_latex_hold_the_same_numbers_as_the_markdown(report):
    for name in ("table1", "table2", "table3", "table4"):
        blocks = markdown_blocks(report.out / f"{name}.md")
        with (report.out / f"{name}.csv").open(newline="") as f:
            table = list(csv.reader(f))
        tex = latex_rows(report.out / f"{name}.tex")
        header = table[0]
        extra = ("reduction %", " std", " n")
        numbers_at = [j for j, h in enumerate(header) if j > 1 and not h.endswith(extra)]
        assert all(header[j + 1] == f"{header[j]} std" for j in numbers_at)
        assert len(table) - 1 == sum(len(rows) for _, rows in blocks.values()) == len(tex)
        for row in table[1:]:
            title, label = row[0], row[1]
            md_header, md_rows = blocks[title]
            cells = md_rows.get(label) or md_rows[f"{label} ▼"]
            assert len(numbers_at) == len(cells) == len(md_header) - 1
            tex_cells = []
            for j, cell in zip(numbers_at, cells, strict=True):
                shown, mark = parse(cell)
                assert (shown is None) == (row[j] == ""), (name, label, cell, row[j])
                if shown is not None:
                    decimals = len(shown.split(".")[1])
                    assert f"{float(row[j]):.{decimals}f}" == shown, (name, label)
                    n = int(row[j + 2])
                    assert (row[j + 1] != "") == (n > 1), (name, label)  # std from 2 runs
                    assert (f", n={n})" in cell) == (n > 1), (name, label, cell)
                wrap = {"best": r"\textbf{{{}}}", "second": "[{}]"}.get(mark, "{}")
                tex_cells.append("—" if shown is None else wrap.format(shown))
            assert [c.split(" (")[0] for c in tex[title, label]] == tex_cells, (name, label)


@pytest.mark.slow
def test_table2_and_the_cost_tables(report, runs, store):
    blocks = markdown_blocks(report.out / "table2.md")
    header, rows = blocks["W/O augmentation"]
    assert list(rows) == TABLE2 and len(header) == 1 + 2 * 2 * len(SCORES)
    after1 = ("Loss ▼", "RMSE ▼", "PCC ▲", "CCC ▲")
    assert header[1:5] == [f"2 clients · After Task 1 · {h}" for h in after1]
    assert header[5] == "2 clients · After Task 2 · Loss ▼"
    lgr = metrics_of(store, runs["FedLGR"])
    expected = [f"{lgr[f'after_task{k}/test/{m}']:.3f}" for k in (1, 2) for m in SCORES]
    assert [parse(c) for c in rows["FedLGR"][: 2 * len(SCORES)]] == [(v, "best") for v in expected]
    assert rows["FedAvg-EWC"] == ["—"] * 2 * 2 * len(SCORES)

    header, rows = markdown_blocks(report.out / "table3.md")["2 clients, W/O augmentation"]
    assert header[1:5] == ["FedAvg", "FedRootAvg", "FedBN", "FedRootBN"]
    full, root = metrics_of(store, runs["FedAvg"]), metrics_of(store, runs["FedRootAvg"])
    cpu = rows["CPU usage (s) ▼"]
    cut = reduction_percent(full["mean/cost/cpu_s"], root["mean/cost/cpu_s"])
    arrow = "▼" if cut >= 0 else "▲"
    assert cpu[1].endswith(f"({arrow} {abs(cut):.1f}%)")
    marks = mark_lower_of_pair(full["mean/cost/cpu_s"], root["mean/cost/cpu_s"], 2)
    assert [parse(c)[1] for c in cpu[:2]] == marks
    assert parse(cpu[0])[0] == f"{full['mean/cost/cpu_s']:.2f}"
    assert cpu[2:4] == ["—", "—"]  # FedBN's run failed
    if "mean/cost/gpu_util" not in full:  # no NVIDIA GPU here: not measured
        assert rows["GPU usage (%) ▼"][:2] == ["—", "—"]

    header, rows = markdown_blocks(report.out / "table4.md")["2 clients, W/O augmentation"]
    assert header[1:] == [
        "FedAvg-EWC",
        "FedRoot-EWC",
        "FedAvg-EWCOnline",
        "FedRoot-EWCOnline",
        "FedAvg-SI",
        "FedRoot-SI",
        "FedAvg-MAS",
        "FedRoot-MAS",
        "FedAvg-NR",
        "FedRoot-NR",
        "FedLGR",
    ]
    assert rows["CPU usage (s) ▼"][-1] == f"{lgr['mean/cost/cpu_s']:.2f}"  # no pair, no mark


@pytest.mark.slow
def test_report_is_logged_back_to_mlflow(report, store):
    client = mlflow.MlflowClient(store)
    run = client.get_run(report.logged_to)
    assert run.info.run_name == "report" and run.info.status == "FINISHED"
    assert run.data.tags["fedlgr.kind"] == "report"
    logged = {
        a.path.removeprefix("report/") for a in client.list_artifacts(run.info.run_id, "report")
    }
    tables = {f"table{k}{s}" for k in (1, 2, 3, 4) for s in (".md", ".tex", ".csv")}
    plots = {"fl_curves.png", "fcl_curves.png", "forgetting.png", "fl_costs.png", "fcl_costs.png"}
    assert tables | plots <= logged and set(report.plots) == plots
    assert (report.out / "fl_curves.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow
def test_cli_reports_again_without_counting_report_runs(report, store, tmp_path, capsys):
    out = tmp_path / "again"
    args = ["report", "--tracking-uri", store, "--experiment", EXPERIMENT, "--out", str(out)]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "Report on 5 finished runs of experiment `report-test`" in text  # not the report run
    assert "table1 (FL results)" in text and "from 4 runs" in text and str(out) in text
    assert (out / "table1.md").read_text(encoding="utf-8") == (report.out / "table1.md").read_text(
        encoding="utf-8"
    )


def test_cli_names_an_unknown_experiment_in_one_line(store, capsys):
    open_client(store)  # a store that exists, whichever of this module's tests ran before
    assert main(["report", "--tracking-uri", store, "--experiment", "nope"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.startswith("fedlgr: error: no MLflow experiment named 'nope'")


def test_an_empty_store_file_is_refused_and_left_empty(tmp_path, capsys):
    """The seventh fault sweep (p01): a read-only command wrote MLflow's schema into an
    existing 0-byte file (a missing one was refused)."""
    empty = tmp_path / "empty.db"
    empty.touch()
    assert main(["report", "--tracking-uri", f"sqlite:///{empty}", "--experiment", "x"]) == 1
    assert capsys.readouterr().err.strip() == (
        f"fedlgr: error: no MLflow store at sqlite:///{empty}: {empty} is an empty file"
    )
    assert empty.stat().st_size == 0


# --------------------------------------------------------------------------- sweeps


def _finished_run(client, experiment_id, tags, metrics) -> str:
    run_id = client.create_run(experiment_id, tags=tags).info.run_id
    for key, value in metrics.items():
        client.log_metric(run_id, key, value, step=1)
    client.set_terminated(run_id, "FINISHED")
    return run_id


def test_sweep_report_shows_the_best_trial_per_cell_and_goes_into_the_parent_run(store, tmp_path):
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("sweeps", artifact_location=tmp_path.as_uri())
    tags = {"method": "FedAvg-EWC", "benchmark": "FCL", "clients": "2", "augmentation": "false"}
    # The parent run, finished and holding the best trial's tags and score, is not a trial.
    parent = _finished_run(
        client,
        experiment_id,
        {**tags, "fedlgr.kind": "sweep", "sweep": "s1", "objective": "minimize test/loss"},
        {"after_task1/test/loss": 0.2},
    )
    for trial, (loss, cpu) in enumerate([(0.2, 10.0), (0.4, 30.0)]):
        swept = json.dumps({"method": "FedAvg-EWC", "continual.ewc.lambda_": 10**trial})
        trial_tags = {
            **tags,
            "sweep": "s1",
            "trial": str(trial),
            "mlflow.parentRunId": parent,
            "swept": swept,
        }
        _finished_run(
            client,
            experiment_id,
            trial_tags,
            {"after_task1/test/loss": loss, "test/loss": loss + 1, "mean/cost/cpu_s": cpu},
        )
    _finished_run(client, experiment_id, {**tags, "sweep": "s2"}, {"after_task1/test/loss": 9.0})

    result = make_report(store, sweep="s1", out=tmp_path / "out")
    # The grid's best trial by the sweep's objective (test/loss: trial 0), not the mean.
    assert result.runs == 1 and [n for n, _ in result.tables] == ["table2", "table4"]
    header, rows = markdown_blocks(tmp_path / "out" / "table2.md")["W/O augmentation"]
    # ... and the value it won with (the method places it in the cell: not repeated). A
    # sweep's table has only the rows and columns that hold values: its one method, the
    # one score its trials logged.
    assert header == ["Method", "2 clients · After Task 1 · Loss ▼"]
    assert rows == {"FedAvg-EWC": ["**0.200** (ewc.lambda_=1)"]}
    _, rows = markdown_blocks(tmp_path / "out" / "table4.md")["2 clients, W/O augmentation"]
    assert rows["CPU usage (s) ▼"][0] == "10.00 (ewc.lambda_=1)"
    assert result.logged_to == parent
    logged = {a.path for a in client.list_artifacts(parent, "report")}
    assert {"report/table2.md", "report/table4.csv"} <= logged

    with pytest.raises(ReportError, match="sweep `nothing` has no finished fedlgr runs"):
        make_report(store, sweep="nothing", out=tmp_path / "none")


def test_runs_of_several_datasets_must_be_told_apart(store, tmp_path):
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("mixed", artifact_location=tmp_path.as_uri())
    for dataset, loss in (("synthetic", 0.5), ("manners-db", 0.3)):
        tags = {
            "method": "FedAvg",
            "benchmark": "FL",
            "clients": "2",
            "augmentation": "false",
            "dataset": dataset,
            "modality": "image",
        }
        _finished_run(client, experiment_id, tags, {"test/loss": loss})
    with pytest.raises(ReportError, match=r"mixes datasets.*--dataset"):
        make_report(store, experiment="mixed", out=tmp_path / "a", log=False)
    result = make_report(
        store, experiment="mixed", dataset="manners-db", out=tmp_path / "b", log=False
    )
    assert result.runs == 1 and result.logged_to is None
    _, rows = markdown_blocks(tmp_path / "b" / "table1.md")["W/O augmentation"]
    assert rows["FedAvg"][0] == "**0.300**"


# --------------------------------------------------------------------------- replicates


def _tracked_run(client, experiment_id, overrides, metrics, *, start, tags=None) -> str:
    """A FINISHED run as the Tracker writes one - the config's tags, its flattened config as
    params, the final metrics - without training; started at ``start`` (ms)."""
    config = load_config(None, overrides)
    run_tags = {
        "method": config.method_name,
        "benchmark": "FCL" if config.continual_learning else "FL",
        "clients": str(config.data.clients),
        "augmentation": str(config.data.augment).lower(),
        "dataset": "synthetic",
        "modality": config.data.modality,
        "fedlgr.config_hash": config_hash(config),
        **(tags or {}),
    }
    run_id = client.create_run(experiment_id, start_time=start, tags=run_tags).info.run_id
    for key, value in run_params(config).items():
        client.log_param(run_id, key, value)
    for key, value in metrics.items():
        client.log_metric(run_id, key, value, step=1)
    client.set_terminated(run_id, "FINISHED")
    return run_id


def _scores(rmse: float) -> dict[str, float]:
    return {"test/loss": rmse**2, "test/rmse": rmse, "test/pcc": 0.5}


def test_runs_of_one_cell_with_other_rounds_are_refused_naming_the_setting(
    store, tmp_path, monkeypatch, capsys
):
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("rounds", artifact_location=tmp_path.as_uri())
    # A 5-round run and two 20-round seeds; tracking.* and runtime.* differ too, and the
    # seeds: none of them splits a cell.
    plans = [
        (["federated.rounds=5", "seed=0", "runtime.threads=1"], 0.9),
        (["federated.rounds=20", "seed=0", "tracking.run_name=a"], 0.5),
        (["federated.rounds=20", "seed=1", "data.seed=3", "runtime.threads=2"], 0.7),
    ]
    for k, (overrides, rmse) in enumerate(plans):
        _tracked_run(client, experiment_id, ["method=FedAvg", *overrides], _scores(rmse), start=k)
    capsys.readouterr()  # MLflow's own log of creating the store, when this test runs first

    uri = ["report", "--tracking-uri", store, "--experiment", "rounds", "--no-log"]
    assert main([*uri, "--out", str(tmp_path / "mixed")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.startswith(
        "fedlgr: error: experiment `rounds`: the cell FL FedAvg, 2 clients, without "
        "augmentation holds runs of other settings than their seeds: "
        "federated.rounds (20: 2 runs, 5: 1 run)."
    )
    assert "--where federated.rounds=" in err
    assert "runtime." not in err and "tracking.run_name" not in err and "data.seed (" not in err

    # Reported apart: the 20-round runs are two seeds of one setting, averaged.
    monkeypatch.chdir(tmp_path)  # the default folder is the filter's own
    assert main([*uri, "--where", "federated.rounds=20"]) == 0
    out = Path("reports", "rounds", "federated.rounds=20")
    assert str(out) in capsys.readouterr().out
    _, rows = markdown_blocks(out / "table1.md")["W/O augmentation"]
    assert rows["FedAvg"][1] == f"**0.600** (± {statistics.stdev([0.5, 0.7]):.3f}, n=2)"
    assert "experiment `rounds` (federated.rounds=20)" in (out / "table1.md").read_text()


def test_two_runs_of_one_seed_are_one_replicate_the_newest_kept(store, tmp_path):
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("repeats", artifact_location=tmp_path.as_uri())
    older = _tracked_run(client, experiment_id, ["method=FedAvg"], _scores(0.9), start=1000)
    newer = _tracked_run(client, experiment_id, ["method=FedAvg"], _scores(0.5), start=2000)

    result = make_report(store, experiment="repeats", out=tmp_path / "out", log=False)
    assert result.runs == 1
    _, rows = markdown_blocks(tmp_path / "out" / "table1.md")["W/O augmentation"]
    assert rows["FedAvg"][1] == "**0.500**"  # the newest run's value, n=1: no spread
    with (tmp_path / "out" / "table1.csv").open(newline="") as f:
        fedavg = next(r for r in csv.DictReader(f) if r["method"] == "FedAvg")
    assert fedavg["2c/test/rmse n"] == "1" and float(fedavg["2c/test/rmse"]) == 0.5
    said = [n for n in result.notes if "repeat" in n]
    assert len(said) == 1 and result.summary().count("repeat the settings and seeds") == 1
    assert f"kept run {newer[:8]}, left out {older[:8]}" in said[0]
    assert said[0] in (tmp_path / "out" / "table1.md").read_text()


def test_an_empty_block_is_left_out(store, tmp_path):
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("no-aug", artifact_location=tmp_path.as_uri())
    _tracked_run(client, experiment_id, ["method=FedRootAvg"], _scores(0.8), start=1)
    make_report(store, experiment="no-aug", out=tmp_path / "out", log=False)
    assert list(markdown_blocks(tmp_path / "out" / "table1.md")) == ["W/O augmentation"]
    assert "W/ augmentation" not in (tmp_path / "out" / "table1.tex").read_text()
    with (tmp_path / "out" / "table1.csv").open(newline="") as f:
        assert {r["augmentation"] for r in csv.DictReader(f)} == {"W/O augmentation"}


@pytest.mark.slow
def test_two_studies_of_one_sweep_are_reported_apart(store, tmp_path, monkeypatch, capsys):
    """The same sweep launched twice on fresh Optuna storages: two studies of one name,
    each with its parent run, in one MLflow store."""
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("twice", artifact_location=tmp_path.as_uri())
    sweep = {"sweep": "twice", "study": "twice"}
    parents = []
    for start, trials in ((1000, [("0.01", 0.3)]), (5000, [("0.01", 0.8), ("0.001", 0.6)])):
        parent = _finished_run(
            client,
            experiment_id,
            {**sweep, "fedlgr.kind": "sweep", "objective": "minimize test/rmse"},
            {},
        )
        client.update_run(parent, status="FINISHED")
        parents.append(parent)
        for k, (lr, rmse) in enumerate(trials):
            tags = {
                **sweep,
                "fedlgr.kind": "trial",
                "trial": str(k),
                "mlflow.parentRunId": parent,
                "swept": json.dumps({"train.lr_top": float(lr)}),
            }
            overrides = ["method=FedAvg", f"train.lr_top={lr}"]
            _tracked_run(
                client, experiment_id, overrides, _scores(rmse), start=start + k, tags=tags
            )
    # The parents' start times: the second launch is the newer one.
    old, new = parents
    assert client.get_run(old).info.start_time <= client.get_run(new).info.start_time

    monkeypatch.chdir(tmp_path)
    assert main(["report", "--tracking-uri", store, "--sweep", "twice"]) == 0
    printed = capsys.readouterr().out
    folder = Path("reports", "sweeps", "twice", f"twice-{new[:8]}")
    _, rows = markdown_blocks(folder / "table1.md")["W/O augmentation"]
    # Only the newest study's trials: its best (0.6), not the other study's 0.3.
    assert rows["FedAvg"][1] == "**0.600** (lr_top=0.001)"
    assert printed.count("has 2 studies in this store") == 1
    assert f"reported the newest, study `twice` (parent run {new}" in printed
    assert f"not reported: study `twice` (parent run {old}" in printed
    assert "--study" in printed
    assert f"logged to MLflow run {new} under report/" in printed
    assert {a.path for a in client.list_artifacts(new, "report")} >= {"report/table1.md"}
    assert client.list_artifacts(old, "report") == []

    result = make_report(store, sweep="twice", study=old[:8], out=tmp_path / "old")
    assert result.runs == 1 and result.logged_to == old
    assert result.source == "sweep `twice`, study `twice`"
    _, rows = markdown_blocks(tmp_path / "old" / "table1.md")["W/O augmentation"]
    assert rows["FedAvg"][1] == "**0.300** (lr_top=0.01)"
    with pytest.raises(ReportError, match="sweep `twice` has no study 'nope'"):
        make_report(store, sweep="twice", study="nope", out=tmp_path / "none")


@pytest.mark.slow
def test_runs_under_dp_are_rows_of_their_own_naming_epsilon_noise_and_clip(store, tmp_path):
    """FedAvg plain and under two noise multipliers: three rows, the DP ones named by the
    epsilon they spent; two seeds of one DP setting are averaged in one row."""
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("private", artifact_location=tmp_path.as_uri())
    dp = ["federated.dp.clip=0.5", "federated.dp.delta=0.01"]
    plans = [
        (["method=FedAvg"], _scores(0.5)),
        ([*dp, "federated.dp.noise_multiplier=1"], _scores(0.8) | {"privacy/epsilon": 3.456}),
        (
            [*dp, "federated.dp.noise_multiplier=1", "seed=1"],
            _scores(0.6) | {"privacy/epsilon": 3.456},
        ),
        ([*dp, "federated.dp.noise_multiplier=4"], _scores(0.9) | {"privacy/epsilon": 0.5}),
    ]
    for k, (overrides, metrics) in enumerate(plans):
        _tracked_run(client, experiment_id, overrides, metrics, start=k)
    make_report(store, experiment="private", out=tmp_path / "out", log=False)
    _, rows = markdown_blocks(tmp_path / "out" / "table1.md")["W/O augmentation"]
    assert rows["FedAvg"][1] == "**0.500**"
    assert rows["FedAvg, DP ε=3.46 (z=1.0, C=0.5)"][1].startswith("[0.700] (± 0.141, n=2)")
    assert rows["FedAvg, DP ε=0.50 (z=4.0, C=0.5)"][1] == "0.900"


def test_paper_rows_give_the_published_values_under_each_method_unmarked(store, tmp_path):
    """``--paper``: FedAvg's run, then the paper's FedAvg (Table I, W/O augmentation: 2
    clients loss 0.264, RMSE 0.510, PCC 0.508; 10 clients 0.220, 0.467, 0.487), never marked
    best; the paper's FedProx row under no run of it still shows; Table II's FedLGR row."""
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("side", artifact_location=tmp_path.as_uri())
    _tracked_run(client, experiment_id, ["method=FedAvg"], _scores(0.9), start=1)
    fcl = ["method=FedLGR", "continual.rounds_per_task=1"]
    _tracked_run(client, experiment_id, fcl, {"after_task2/test/rmse": 0.7}, start=2)
    assert main(["report", "--tracking-uri", store, "--experiment", "side", "--no-log",
                 "--paper", "--out", str(tmp_path / "out")]) == 0  # fmt: skip
    header, rows = markdown_blocks(tmp_path / "out" / "table1.md")["W/O augmentation"]
    names = list(rows)
    assert names.index("FedAvg (paper)") == names.index("FedAvg") + 1
    assert rows["FedAvg"][1] == "**0.900**"
    assert rows["FedAvg (paper)"][:3] == ["0.264", "0.510", "0.508"]
    ten = header.index("10 clients · RMSE ▼") - 1
    assert rows["FedAvg (paper)"][ten] == "0.467"
    assert rows["FedAvg (paper)"][3] == "—"  # the paper has no CCC
    assert rows["FedProx (paper)"][:3] == ["0.262", "0.507", "0.513"]  # unmarked
    text = (tmp_path / "out" / "table1.md").read_text()
    assert "published values (Churamani et al. 2024, arXiv:2405.15773, Table I" in text
    _, rows2 = markdown_blocks(tmp_path / "out" / "table2.md")["W/O augmentation"]
    after = ["0.252", "0.499", "0.599", "—", "0.465", "0.677", "0.534", "—"]  # no CCC
    assert rows2["FedLGR (paper)"][:8] == after


# --------------------------------------------------------------------------- plots


def test_every_headline_score_is_drawn_where_pcc_is(store, tmp_path):
    """test/ccc was logged but missing from the report's plots: every panel drawn for PCC
    has its CCC twin, and every headline score has its curves and forgetting bars."""
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("headline", artifact_location=tmp_path.as_uri())
    for benchmark, method in (("FL", "FedAvg"), ("FCL", "FedAvg-EWC")):
        tags = {"method": method, "benchmark": benchmark, "clients": "2", "augmentation": "false"}
        logged = {f"test/{m}": 0.5 for m in SCORES}
        logged |= {f"after_task1/task/circle/{m}": 0.5 for m in SCORES}
        logged |= {f"after_task2/forgetting/circle/{m}": 0.1 for m in SCORES}
        _finished_run(client, experiment_id, tags, logged)
    with drawn_figures() as drawn:
        report = make_report(store, experiment="headline", out=tmp_path / "out", log=False)
    assert report.plots == ["fl_curves.png", "fcl_curves.png", "forgetting.png"]
    assert drawn["FL: test scores per round"] == ["test RMSE", "test PCC", "test CCC"]
    assert drawn["FCL: test scores per round"] == ["test RMSE", "test PCC", "test CCC"]
    forgetting = "FCL: forgetting of Task 1 after the last task (positive = forgotten)"
    assert drawn[forgetting] == [f"forgetting of Task 1, {m}" for m in ("RMSE", "PCC", "CCC")]


def test_a_report_folder_that_is_a_file_is_one_line(tmp_path, monkeypatch, capsys):
    """A bad input of issue 20 (points 8 and 9)."""
    # no store is needed to reach the folder: the runs are stood in for
    selection = report_runs.Selection(
        client=None,
        uri="sqlite:///x",
        name="exp",
        source="experiment `exp`",
        experiment_ids=[],
        sweep=None,
        records=[],
    )
    monkeypatch.setattr(report_runs, "open_store", lambda uri: None)
    monkeypatch.setattr(report_runs, "select_runs", lambda *a, **k: selection)
    file = tmp_path / "report.md"
    file.write_text("not a folder")
    uri = ["--tracking-uri", "sqlite:///x", "--no-log"]
    for out, why in ((file, "is a file"), (file / "sub", f"lies under {file}, a file")):
        assert main(["report", "--out", str(out), *uri]) == 1
        err = capsys.readouterr().err
        assert err == f"fedlgr: error: {out}: {why}; the report (--out) is a folder of " + (
            "tables and plots: name a new or existing folder\n"
        )
    monkeypatch.chdir(tmp_path)  # the default folder, reports/exp, is a file too
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "exp").write_text("")
    assert main(["report", *uri]) == 1
    assert "reports/exp: is a file" in capsys.readouterr().err


def test_a_run_with_faults_partial_participation_or_refusals_is_labelled_as_such():
    """Issue 50's fault sweep: ``fedlgr report`` printed a plain ``FedRootMedian | 1.172`` row
    for a run with 4 label-poisoning clients of 10; runs with simulated faults or partial
    participation were not labelled (DP runs were)."""

    def label(params: dict, tags: dict | None = None, metrics: dict | None = None) -> str:
        tags = {"method": "FedRootMedian", **(tags or {})}
        return report_runs.RunRecord("r", "0", tags, metrics or {}, params).method

    poisoned = {"data.clients": "10", "federated.faults.byzantine": "4"}
    poisoned["federated.faults.attack"] = "labels"
    assert label(poisoned) == "FedRootMedian, 4/10 byzantine (labels)"
    assert label({"federated.faults.byzantine": "0", "federated.fraction": "1.0"}) == (
        "FedRootMedian"
    )
    dropped = {"federated.faults.dropout": "0.2", "federated.fraction": "0.5"}
    assert label(dropped) == "FedRootMedian, dropout 0.2, fraction 0.5"
    refused = {"fedlgr.not_taken": "round 1: robot2 (client 2) (upload: ...)"}
    assert label({}, refused) == "FedRootMedian, uploads refused"
    dp = {"federated.dp.noise_multiplier": "1.0", "federated.dp.clip": "0.5"}
    dp["federated.faults.straggler"] = "0.1"
    assert label(dp, metrics={"privacy/epsilon": 3.456}) == (
        "FedRootMedian, DP ε=3.46 (z=1.0, C=0.5), stragglers 0.1"
    )
