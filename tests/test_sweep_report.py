"""``fedlgr report --sweep``: a row per trial (``trials.md``/``.csv``) read back from the
study's Optuna storage, Optuna's plots logged to the study's parent run, and paper tables
without the rows and columns no trial filled; MLflow's trials where the storage is gone."""

from __future__ import annotations

import csv
import json

import mlflow
import optuna
import pytest

from fedlgr.shell.cli import main
from fedlgr.shell.config import CONF_DIR
from fedlgr.shell.report import make_report
from fedlgr.shell.sweep import load_sweep, run_sweep
from tests.support.report import markdown_blocks

FEATURES = CONF_DIR / "debug" / "fast.yaml"  # the features modality: a trial in ~1 s
LR = [0.001, 0.01, 0.1]
HEADER = [
    "trial",
    "train.lr_top",
    "objective: test/rmse",
    "test/rmse",
    "test/pcc",
    "test/ccc",
    "state",
]


@pytest.fixture(scope="module")
def swept(synth_dir, tmp_path_factory):
    """A real 3-point grid over one coefficient (FedAvg's top learning rate) on the fast
    features config, and its report."""
    tmp = tmp_path_factory.mktemp("sweep-report")
    path = tmp / "lr.yaml"
    path.write_text(
        f"base: {FEATURES}\n"
        f"overrides: [method=FedAvg, data.path={synth_dir}, federated.rounds=2]\n"
        "objective: {metric: test/rmse, direction: minimize}\n"
        f"space:\n  train.lr_top: {LR}\n"
    )
    storage, store = f"sqlite:///{tmp}/optuna.db", f"sqlite:///{tmp}/mlflow.db"
    result = run_sweep(load_sweep(path), storage=storage, tracking_uri=store, echo=print)
    report = make_report(store, sweep="lr", out=tmp / "report")
    return result, report, storage, store


def read_csv(path):
    with path.open(newline="", encoding="utf-8") as f:
        return list(csv.reader(f))


@pytest.mark.slow
def test_the_trials_table_is_the_studys_trials_best_first_with_their_scores(swept):
    _, report, storage, store = swept
    study = optuna.load_study(study_name="lr", storage=storage)
    trials = sorted(study.get_trials(), key=lambda t: t.value)  # minimize: lowest first
    assert [t.state.name for t in trials] == ["COMPLETE"] * 3
    header, *rows = read_csv(report.out / "trials.csv")
    assert header == HEADER
    assert [int(r[0]) for r in rows] == [t.number for t in trials]
    client = mlflow.MlflowClient(store)
    for row, trial in zip(rows, trials, strict=True):
        assert float(row[1]) == trial.params["train.lr_top"]
        assert float(row[2]) == trial.value  # written as repr: the same float
        metrics = client.get_run(trial.user_attrs["mlflow_run_id"]).data.metrics
        assert [float(v) for v in row[3:6]] == [
            metrics[f"test/{m}"] for m in ("rmse", "pcc", "ccc")
        ]
        assert row[6] == "COMPLETE"
    assert sorted(float(r[1]) for r in rows) == LR  # every grid point, once
    text = (report.out / "trials.md").read_text(encoding="utf-8")
    lines = [line for line in text.splitlines() if line.startswith("| ")]
    heads = ["trial", "lr_top", "objective: test/rmse ▼", "test RMSE ▼", "test PCC ▲", "test CCC ▲"]
    assert lines[0] == "| " + " | ".join([*heads, "state"]) + " |"
    best = trials[0]
    assert lines[2].startswith(
        f"| **{best.number}** | **{best.params['train.lr_top']}** | **{best.value:.4f}** |"
    )
    assert f"Read from the Optuna storage {storage}" in text
    assert report.sweep.trials == 3 and report.sweep.source == f"Optuna storage {storage}"


@pytest.mark.slow
def test_optunas_plots_are_pngs_logged_to_the_parent_run_and_the_rest_said_why_not(swept):
    result, report, _, store = swept
    assert report.logged_to == result.parent_run_id
    drawn = ["optuna_history.png", "optuna_slice.png"]
    assert report.sweep.plots == drawn and set(drawn) <= set(report.plots)
    for name in drawn:
        assert (report.out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    client = mlflow.MlflowClient(store)
    logged = {a.path for a in client.list_artifacts(result.parent_run_id, "report")}
    assert {f"report/{n}" for n in [*drawn, "trials.md", "trials.csv"]} <= logged
    # one swept setting: no importances, no contour, and the report says so
    assert not (report.out / "optuna_importances.png").exists()
    assert not (report.out / "optuna_contour.png").exists()
    said = "\n".join(report.sweep.notes)
    assert (
        "Parameter importances: not drawn" in said
        and "(this study: 1 varying, 3 completed)" in said
    )
    assert "Contour plot: not drawn" in said and said.splitlines()[0] in report.summary()


@pytest.mark.slow
def test_a_one_coefficient_sweeps_paper_tables_have_no_empty_rows_or_columns(swept):
    _, report, _, _ = swept
    assert [name for name, _ in report.tables] == ["table1", "table3"]
    header, rows = markdown_blocks(report.out / "table1.md")["W/O augmentation"]
    assert list(rows) == ["FedAvg"]  # not the paper's other nine methods as dashes
    assert all(h.startswith("2 clients · ") for h in header[1:]) and len(header) == 5
    assert "—" not in rows["FedAvg"]
    assert rows["FedAvg"][1].endswith("(lr_top=" + rows["FedAvg"][1].split("=")[-1])
    header, rows = markdown_blocks(report.out / "table3.md")["2 clients, W/O augmentation"]
    assert header[1:] == ["FedAvg"] and all("—" not in cells for cells in rows.values())
    with (report.out / "table1.csv").open(newline="") as f:
        assert [r["method"] for r in csv.DictReader(f)] == ["FedAvg"]


@pytest.mark.slow
def test_an_experiment_report_keeps_the_papers_empty_rows(store, tmp_path):
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("one-method", artifact_location=tmp_path.as_uri())
    tags = {"method": "FedAvg", "benchmark": "FL", "clients": "2", "augmentation": "false"}
    run_id = client.create_run(experiment_id, tags=tags).info.run_id
    client.log_metric(run_id, "test/rmse", 0.5, step=1)
    client.set_terminated(run_id, "FINISHED")
    make_report(store, experiment="one-method", out=tmp_path / "out", log=False)
    header, rows = markdown_blocks(tmp_path / "out" / "table1.md")["W/O augmentation"]
    assert len(rows) >= 10 and rows["FedBN"] == ["—"] * (len(header) - 1)
    assert not (tmp_path / "out" / "trials.csv").exists()


# --------------------------------------------------------------------------- two settings


@pytest.fixture
def two_settings(tmp_path):
    """A study of 2 settings x 3 values each (9 trials, a made-up objective: no training),
    each trial with its MLflow run under the study's parent run, as fedlgr sweep leaves
    them."""
    storage, store = f"sqlite:///{tmp_path}/optuna.db", f"sqlite:///{tmp_path}/mlflow.db"
    client = mlflow.MlflowClient(store)
    experiment_id = client.create_experiment("two", artifact_location=tmp_path.as_uri())
    common = {"sweep": "two", "study": "two"}
    parent = client.create_run(
        experiment_id,
        tags={
            **common,
            "fedlgr.kind": "sweep",
            "objective": "minimize test/rmse",
            "storage": storage,
        },
    ).info.run_id
    client.log_param(
        parent, "space", json.dumps({"train.lr_top": [0.01, 0.1, 1.0], "train.epochs": [1, 2, 3]})
    )
    space = {"train.lr_top": [0.01, 0.1, 1.0], "train.epochs": [1, 2, 3]}
    study = optuna.create_study(
        study_name="two", storage=storage, sampler=optuna.samplers.GridSampler(space, seed=0)
    )
    study.set_user_attr("mlflow_parent_run_id", parent)

    def objective(trial):
        lr = trial.suggest_categorical("train.lr_top", space["train.lr_top"])
        epochs = trial.suggest_categorical("train.epochs", space["train.epochs"])
        rmse = 1.0 / epochs + lr
        tags = {
            **common,
            "fedlgr.kind": "trial",
            "trial": str(trial.number),
            "mlflow.parentRunId": parent,
            "method": "FedAvg",
            "benchmark": "FL",
            "clients": "2",
            "augmentation": "false",
            "swept": json.dumps(trial.params),
        }
        run_id = client.create_run(experiment_id, tags=tags).info.run_id
        for name, value in (("rmse", rmse), ("pcc", 1 - rmse), ("ccc", 0.5 - rmse)):
            client.log_metric(run_id, f"test/{name}", value, step=1)
        client.set_terminated(run_id, "FINISHED")
        trial.set_user_attr("mlflow_run_id", run_id)
        return rmse

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study.optimize(objective, n_trials=9)
    client.set_terminated(parent, "FINISHED")
    return store, storage, parent


@pytest.mark.slow
def test_two_settings_get_importances_and_a_contour(two_settings, tmp_path):
    store, _, parent = two_settings
    report = make_report(store, sweep="two", out=tmp_path / "report")
    drawn = [
        "optuna_history.png",
        "optuna_slice.png",
        "optuna_importances.png",
        "optuna_contour.png",
    ]
    assert report.sweep.plots == drawn and report.sweep.notes == []
    assert all((report.out / n).read_bytes()[:4] == b"\x89PNG" for n in drawn)
    logged = {a.path for a in mlflow.MlflowClient(store).list_artifacts(parent, "report")}
    assert {f"report/{n}" for n in drawn} <= logged
    header, *rows = read_csv(report.out / "trials.csv")
    assert header[1:3] == ["train.lr_top", "train.epochs"]  # the sweep's order
    values = [float(r[3]) for r in rows]
    assert values == sorted(values) and values[0] == pytest.approx(1 / 3 + 0.01, abs=1e-12)


@pytest.mark.slow
def test_without_the_storage_the_trials_come_from_mlflow_in_one_line(
    two_settings, tmp_path, capsys
):
    store, _, _ = two_settings
    gone = f"sqlite:///{tmp_path}/elsewhere/optuna.db"
    out = tmp_path / "report"
    args = [
        "report",
        "--tracking-uri",
        store,
        "--sweep",
        "two",
        "--storage",
        gone,
        "--out",
        str(out),
    ]
    assert main(args) == 0
    printed = capsys.readouterr().out
    said = [line for line in printed.splitlines() if "read from MLflow" in line]
    assert len(said) == 1 and f"no file {tmp_path}/elsewhere/optuna.db here" in said[0]
    assert not (tmp_path / "elsewhere").exists()  # nothing created where the storage was not
    _, *rows = read_csv(out / "trials.csv")
    assert len(rows) == 9 and {r[-1] for r in rows} == {"COMPLETE"}
    assert [float(r[3]) for r in rows] == sorted(float(r[3]) for r in rows)
    assert not (out / "optuna_slice.png").exists()
