"""What a researcher sees of the runs in MLflow (issue 13, points 1, 3 and 6): the printed
link opens the experiment's runs table, runs are told apart (names, context tags, dataset,
system metrics, no machine-local params), and an unreachable server fails at once."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from fedlgr.shell.cli import main
from fedlgr.shell.config import load_config
from fedlgr.shell.tracking.context import run_name, trial_config
from fedlgr.shell.tracking.mlflow_run import headline_first
from fedlgr.shell.tracking.store import runs_hint
from tests.support.chromium import CHROMIUM, rendered
from tests.support.ports import free_port
from tests.support.runs import FAST

REPO = Path(__file__).resolve().parent.parent
VIEW = "runs?workflowType=machine_learning&viewStateShareKey=fedlgr"
LINK = re.compile(rf"(http://\S+)/#/experiments/(\d+)/{re.escape(VIEW)}")


def rest(server: str, endpoint: str, body: dict | None = None, **query) -> dict:
    """One call to MLflow's REST API (GET with ``query``, POST with ``body``)."""
    url = f"{server}/api/2.0/mlflow/{endpoint}"
    if query:
        url += "?" + urllib.parse.urlencode(query)
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(url, data, {"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as answer:
        return json.load(answer)


def fast_run_on(server: str, synth_dir, cache_dir, *overrides: str) -> None:
    """``fedlgr run`` of the fast config with ``overrides``, logging to ``server``."""
    data = [f"data.path={synth_dir}", f"data.cache_dir={cache_dir}"]
    assert main(["run", str(FAST), *data, *overrides, "--tracking-uri", server]) == 0


@pytest.mark.slow
def test_runs_on_a_server_are_told_apart_and_the_printed_link_opens_their_experiment(
    mlflow_server,
    synth_dir,
    cache_dir,
    tmp_path_factory,
    capsys,
):
    links = []
    for modality in ("image", "features"):
        fast_run_on(
            mlflow_server,
            synth_dir,
            cache_dir,
            f"data.modality={modality}",
            "tracking.experiment=ui-e2e",
            "tracking.system_metrics_s=1",
            "runtime.threads=1",
        )
        links += LINK.findall(capsys.readouterr().out)
    experiment = rest(mlflow_server, "experiments/get-by-name", experiment_name="ui-e2e")
    experiment_id = experiment["experiment"]["experiment_id"]
    assert links == [(mlflow_server, experiment_id)] * 2
    kind = {t["key"]: t["value"] for t in experiment["experiment"]["tags"]}
    assert kind["mlflow.experimentKind"] == "custom_model_development"  # the UI shows runs
    with urllib.request.urlopen(mlflow_server + "/", timeout=30) as page:  # the UI is there
        assert b"<html" in page.read().lower()

    runs = rest(mlflow_server, "runs/search", {"experiment_ids": [experiment_id]})["runs"]
    assert len(runs) == 2
    names = sorted(r["info"]["run_name"] for r in runs)
    assert names == [
        f"{run_name_prefix(synth_dir, cache_dir)}-features",
        f"{run_name_prefix(synth_dir, cache_dir)}-image",
    ]
    local = [str(tmp_path_factory.getbasetemp()), str(synth_dir), str(cache_dir)]
    for run in runs:
        tags = {t["key"]: t["value"] for t in run["data"]["tags"]}
        assert tags["mlflow.source.type"] == "LOCAL" and tags["mlflow.source.name"]
        assert tags["mlflow.user"]
        commit = tags["mlflow.source.git.commit"]
        assert re.fullmatch(r"[0-9a-f]{40}", commit)
        known = subprocess.run(["git", "cat-file", "-e", f"{commit}^{{commit}}"], cwd=REPO)
        assert known.returncode == 0, commit  # a commit of this checkout
        params = {p["key"]: p["value"] for p in run["data"]["params"]}
        assert "data.cache_dir" not in params and "tracking.uri" not in params
        assert "data.clients" in params
        assert not [(k, v) for k, v in params.items() if any(p in v for p in local)]
        (given,) = run["inputs"]["dataset_inputs"]
        dataset = given["dataset"]
        assert dataset["name"] == "synthetic" and dataset["digest"]
        assert json.loads(dataset["source"])["uri"] == str(Path(synth_dir).resolve())
        assert json.loads(dataset["profile"])["num_rows"] == 48
        inputs = {t["key"]: t["value"] for t in given["tags"]}
        assert inputs["modality"] == tags["modality"]
        metrics = {m["key"] for m in run["data"]["metrics"]}
        assert {"system/cpu_utilization_percentage", "system/system_memory_usage_megabytes"} <= (
            metrics
        )


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium here (.ci/run installs Debian's)")
@pytest.mark.slow
def test_the_printed_link_shows_the_runs_table_in_headless_chromium(
    mlflow_server,
    synth_dir,
    cache_dir,
    tmp_path,
    capsys,
):
    for method in ("FedAvg", "FedRootAvg"):
        fast_run_on(
            mlflow_server,
            synth_dir,
            cache_dir,
            "data.modality=features",
            f"method={method}",
            "tracking.experiment=ui-browser",
            "tracking.system_metrics=false",
        )
    out = capsys.readouterr().out
    (link,) = {m.group(0) for m in LINK.finditer(out)}
    experiment_id = LINK.search(out).group(2)
    # What a browser that never saw this server renders at the printed link.
    dom = rendered(link, tmp_path / "profile")
    assert "<strong>2</strong> matching runs" in dom, dom[-3000:]
    runs = rest(mlflow_server, "runs/search", {"experiment_ids": [experiment_id]})["runs"]
    for run in runs:  # each run is a row that links to it, under its name
        row = f'href="#/experiments/{experiment_id}/runs/{run["info"]["run_id"]}"'
        assert row in dom and f">{run['info']['run_name']}</span>" in dom
    # fedlgr's shared view: the headline figures are columns of the runs table ...
    assert "shared view" in dom
    for metric in ("test/rmse", "test/pcc", "test/ccc", "mean/cost/cpu_s"):
        assert f">{metric}<" in dom, metric
    # ... and the first charts of the chart view: the per-round curves (the scatter and the
    # parallel-coordinates plot below them are drawn when scrolled to)
    titles = [f">{t}<" for t in ("test/rmse", "test/pcc", "test/ccc")]
    for budget in (15000, 40000):  # a busy machine draws the charts later: wait longer once
        charts = rendered(f"{link}&compareRunsMode=CHART", tmp_path / f"charts{budget}", budget)
        if all(t in charts for t in titles):
            break
    headline = charts.index(">headline<")
    # per-round curves of RMSE, PCC and CCC, their final values' scatter, the parallel plot
    assert charts[headline:].startswith('>headline</div><div class="') and ">(5)<" in charts
    for title in titles:
        assert title in charts and headline < charts.index(title), (title, charts[-3000:])
    # A run's page opens on its headline and summary tables, then its metrics, headline first.
    run_id = runs[0]["info"]["run_id"]
    page = rendered(
        f"{mlflow_server}/#/experiments/{experiment_id}/runs/{run_id}", tmp_path / "run"
    )
    summary = page.index("client    loss   RMSE   PCC")

    def listed(key: str) -> int:  # in the metrics table, below the description
        return page.index(f">{key}<", summary)

    assert listed("test/rmse") < listed("test/pcc") < listed("test/loss")
    assert ">test/rmse/vacuum<" not in page and ">test/client0/rmse<" not in page


def run_name_prefix(synth_dir, cache_dir) -> str:
    """The method and setting part of the fast config's run names (``FedAvg-2c-noaug``)."""
    return load_config(FAST, [f"data.path={synth_dir}", f"data.cache_dir={cache_dir}"]).run_name


def test_an_unreachable_tracking_server_fails_at_once_in_one_line(synth_dir, tmp_path):
    uri = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    start = time.monotonic()
    command = ["run", str(FAST), f"data.path={synth_dir}", "--tracking-uri", uri]
    done = subprocess.run(
        [sys.executable, "-m", "fedlgr", *command],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    seconds = time.monotonic() - start
    assert done.returncode != 0
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and uri in lines[0] and "no MLflow server" in lines[0], done.stderr
    assert seconds < 15, seconds
    assert not (tmp_path / "mlflow.db").exists()


def test_sweep_trials_are_named_after_their_swept_values(synth_dir):
    config = load_config(FAST, [f"data.path={synth_dir}", "method=FedLGR", "data.clients=3"])
    swept = {"train.lr_root": 1e-05, "continual.lgr.replay": "stored", "data.augment": True}
    named = trial_config(config, swept)
    assert run_name(named) == "FedLGR lr_root=1e-05 lgr.replay=stored augment=True"
    # Two swept settings with the same last part keep their full names.
    twins = trial_config(config, {"train.lr": 0.1, "federated.lr": 0.2})
    assert run_name(twins) == "FedLGR train.lr=0.1 federated.lr=0.2"
    # A swept method is named once, by its paper name.
    ewc = load_config(FAST, [f"data.path={synth_dir}", "method=FedRoot-EWC"])
    swept = {"method": "FedRoot-EWC", "continual.ewc.lambda_": 100}
    assert run_name(trial_config(ewc, swept)) == "FedRoot-EWC ewc.lambda_=100"


def test_mlflow_gets_the_headline_metrics_first_and_the_detail_only_if_asked():
    metrics = {
        "round/seconds": 1.0,
        "test/loss": 2.0,
        "test/rmse": 3.0,
        "test/client0/rmse": 3.5,
        "test/rmse/vacuum": 4.0,
        "test/pcc": 0.5,
        "cost/wall_s": 0.2,
        "cost/cpu_s": 0.1,
        "lgr/client1/fd_latent": 0.3,
        "lgr/fd_latent": 0.3,
        "forgetting/circle/rmse": 0.7,
    }
    assert list(headline_first(metrics)) == [
        "test/rmse",
        "test/pcc",
        "test/loss",
        "forgetting/circle/rmse",
        "cost/cpu_s",
        "round/seconds",
        "cost/wall_s",
        "lgr/fd_latent",
    ]
    everything = headline_first(metrics, detail=True)
    assert list(everything)[:5] == list(headline_first(metrics))[:5]
    assert everything == metrics  # the same values, in the headline order


def test_a_local_store_hint_gives_the_ui_command_and_the_runs_link(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    hint = runs_hint("sqlite:///mlflow.db", "7")
    assert f"ui --backend-store-uri sqlite:///{tmp_path}/mlflow.db --port 5000" in hint
    assert hint.endswith(f"http://127.0.0.1:5000/#/experiments/7/{VIEW}")
    server = runs_hint("https://mlflow.example.org/", "3")
    assert server == f"MLflow runs: https://mlflow.example.org/#/experiments/3/{VIEW}"
    assert "***" in runs_hint("postgresql://me:secret@db/mlflow", "1")


@pytest.mark.slow
def test_the_shared_view_gathers_every_sweeps_settings_and_trials(tmp_path):
    import mlflow

    from fedlgr.shell.tracking.experiments import TAG, share_view
    from fedlgr.shell.tracking.mlflow_run import experiment_id

    client = mlflow.MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    eid = experiment_id(client, "views")

    def state() -> dict:
        return json.loads(client.get_experiment(eid).tags[TAG])

    def axes(view: dict) -> list[str]:
        (parallel,) = [c for c in view["compareRunCharts"] if c["type"] == "PARALLEL"]
        return parallel["selectedParams"]

    fresh = state()  # a new experiment has the view at once: its plain runs by method
    assert axes(fresh) == ["method"] and fresh["runsExpanded"] == {}
    assert fresh["selectedColumns"][:2] == ["metrics.`test/rmse`", "metrics.`test/pcc`"]
    assert fresh["orderByKey"] == "metrics.`test/rmse`" and fresh["orderByAsc"] is True
    share_view(client, eid, ["method", "train.lr_top"], "parent-1")
    share_view(client, eid, ["continual.ewc.lambda_"], "parent-2")
    both = state()
    assert axes(both) == ["method", "train.lr_top", "continual.ewc.lambda_"]
    assert both["runsExpanded"] == {"parent-1": True, "parent-2": True}
    assert "params.`continual.ewc.lambda_`" in both["selectedColumns"]
    assert experiment_id(client, "views") == eid and state() == both  # kept as it is
    client.set_experiment_tag(eid, TAG, "not json")  # by hand, or another version
    share_view(client, eid, ["seed"], "parent-3")
    assert axes(state()) == ["method", "seed"] and state()["runsExpanded"] == {"parent-3": True}
