"""The command line: quick help, the data verbs and the interim demo; overrides after options,
MLflow telemetry off unless the user chose, and one error line for a bad argument."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import types
from pathlib import Path

import click
import mlflow
import numpy as np
import pytest
import yaml
from PIL import Image

from fedlgr.shell.cli import command, main, parse
from fedlgr.shell.cli.sweep import shipped_sweeps
from fedlgr.shell.config import CONF_DIR, SWEEPS_DIR, DataConfig, load_config, to_plain
from fedlgr.shell.console import Progress, duration
from fedlgr.shell.data.ratings import read_ratings
from fedlgr.shell.data.splits import make_split
from tests.support.processes import TELEMETRY, child_env, experiment_runs, metric_steps, only_run
from tests.support.runs import FAST


def test_help_does_not_import_heavy_modules():
    """``fedlgr --help`` stays fast because torch & co. load only inside the verbs, and the
    settings (pydantic, OmegaConf) only when a verb reads them."""
    code = (
        "import contextlib, io, sys\n"
        "from fedlgr.shell.cli import main\n"
        "for verb in ([], ['run'], ['sweep'], ['deploy', 'supernode']):\n"
        "    with contextlib.suppress(SystemExit), contextlib.redirect_stdout(io.StringIO()):\n"
        "        main([*verb, '--help'])\n"
        "heavy = [m for m in ('torch', 'torchvision', 'lightning', 'mlflow', 'optuna', 'numpy',"
        " 'flwr', 'pydantic', 'omegaconf') if m in sys.modules]\n"
        "print(heavy)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.stdout.strip() == "[]", done.stderr


def test_help_lists_the_verbs(capsys):
    try:
        main(["--help"])
    except SystemExit as stop:
        assert stop.code == 0
    out = capsys.readouterr().out
    assert "demo" in out and "data" in out


def test_synth_show_and_check(tmp_path, cache_dir, capsys):
    data = tmp_path / "d"
    assert main(["data", "synth", "--out", str(data), "--scenes", "10", "--size", "20"]) == 0
    out = capsys.readouterr().out
    assert "wrote 10 scenes" in out and str(data) in out and "vacuum" in out

    sheet = tmp_path / "sheet.png"
    assert main(["data", "show", str(data), "--out", str(sheet), "--scenes", "6"]) == 0
    assert capsys.readouterr().out.strip() == f"wrote {sheet}"
    with Image.open(sheet) as image:
        assert image.size == (4 * 224, 2 * (224 + 150))  # 6 tiles in rows of 4

    assert main(["data", "check", str(data), "--size", "20", "--clients", "2"]) == 0
    out = capsys.readouterr().out
    assert "10 scenes from" in out and "images 20x20" in out
    assert "client 1" in out and "test (shared)" in out


def test_synth_refuses_a_non_empty_folder(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("mine")
    assert main(["data", "synth", "--out", str(tmp_path), "--scenes", "2"]) == 1
    err = capsys.readouterr().err
    assert err == f"fedlgr: error: {tmp_path}: folder is not empty; pass --force to overwrite it\n"
    assert (tmp_path / "keep.txt").read_text() == "mine"


def test_check_summarises_a_split_of_over_20_clients(synth_dir, cache_dir, capsys):
    """One row per client up to 20; beyond, the first 10 rows and a summary: scenes per
    client (min, median, max) and how many clients hold none of each task."""
    argv = ["data", "check", str(synth_dir), "--modality", "features", "--clients"]
    split = make_split(read_ratings(synth_dir), DataConfig(clients=30))
    sizes = np.array(
        [[len(c.train), len(c.tasks["circle"]), len(c.tasks["arrow"])] for c in split.clients]
    )
    assert main([*argv, "30"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    rows = [line.split() for line in lines if line.startswith("client ")]
    assert rows == [["client", str(c), *map(str, sizes[c])] for c in range(10)]
    assert "(20 more clients)" in lines
    assert lines[-7] == "per client, over all 30 clients:"
    summary = {line[:17].strip(): line[17:].split() for line in lines[-4:]}
    median = [f"{m:g}" for m in np.median(sizes, axis=0)]
    assert summary == {
        "min": [str(v) for v in sizes.min(axis=0)],
        "median": median,
        "max": [str(v) for v in sizes.max(axis=0)],
        "clients with none": [str(v) for v in (sizes == 0).sum(axis=0)],
    }
    assert summary["clients with none"][1:] != ["0", "0"]  # some client lacks a task

    assert main([*argv, "20"]) == 0
    out = capsys.readouterr().out
    assert sum(line.startswith("client ") for line in out.splitlines()) == 20
    assert "more clients" not in out and "per client" not in out


def test_impossible_split_names_the_setting(synth_dir, cache_dir, capsys):
    assert main(["data", "check", str(synth_dir), "--modality", "features", "--clients", "40"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("fedlgr: error: data.clients=40: more clients than the 36 training")


@pytest.mark.slow
def test_demo_synthesises_when_absent_trains_both_methods_and_compares(tmp_path, cache_dir, capsys):
    data = tmp_path / "synth"
    store = f"sqlite:///{tmp_path}/mlflow.db"
    fast = [
        "federated.rounds=1",
        "train.max_batches=2",
        "data.image_size=32",
        "model.width=0.1",
        f"data.cache_dir={cache_dir}",
        "runtime.progress=false",
    ]
    args = ["demo", "--data", str(data), "--scenes", "24", "--tracking-uri", store, *fast]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"no dataset in {data}: synthesising 24 scenes")
    assert "FedAvg-2c-aug-image: 1 rounds" in out and "FedRootAvg-2c-aug-image: 1 rounds" in out
    table = out[out.index("FedAvg vs FedRootAvg") :].splitlines()
    assert table[1].split()[:4] == ["method", "loss", "RMSE", "PCC"]
    assert table[3].startswith("FedAvg ") and table[4].startswith("FedRootAvg ")
    assert_readme_shows_the_demo_table(table)
    import mlflow

    client = mlflow.MlflowClient(store)
    runs = client.search_runs([client.get_experiment_by_name("demo").experiment_id])
    names = [r.info.run_name for r in runs]  # + modality (issue 13), as on the console
    assert sorted(names) == ["FedAvg-2c-aug-image", "FedRootAvg-2c-aug-image"]
    assert all(r.info.status == "FINISHED" for r in runs)
    csv_before = (data / "all_data.csv").read_bytes()
    assert main(args) == 0
    assert "synthesising" not in capsys.readouterr().out
    assert (data / "all_data.csv").read_bytes() == csv_before


def assert_readme_shows_the_demo_table(table: list[str]) -> None:
    """The README's demo table is in the format the demo prints (caption, headers, a row
    per method, CPU seconds and MiB), and its seed-0 scores lie in the ranges over seeds
    it states."""
    import re
    from pathlib import Path

    readme = (Path(__file__).parents[1] / "README.md").read_text(encoding="utf-8")
    shown = readme[readme.index("FedAvg vs FedRootAvg on data/manners-synth after 9") :]
    shown = shown.splitlines()[:5]
    assert shown[0].split(" rounds ", 1)[1] == table[0].split(" rounds ", 1)[1]
    assert shown[1].split() == table[1].split()
    row = re.compile(r"^(FedAvg|FedRootAvg) +(\d\.\d{3}  ){4}\d+\.\d{3}  \d\.\d\d MiB +\d+$")
    assert all(row.match(line) for line in shown[3:5]), shown[3:5]
    assert all(row.match(line) for line in table[3:5]), table[3:5]
    for method in ("FedAvg", "FedRootAvg"):
        stated = re.search(rf"{method} RMSE\s+(\d\.\d+)-(\d\.\d+), PCC (\d\.\d+)-(\d\.\d+)", readme)
        assert stated is not None, method
        low_rmse, high_rmse, low_pcc, high_pcc = map(float, stated.groups())
        values = next(line for line in shown[3:] if line.startswith(f"{method} ")).split()
        assert low_rmse <= float(values[2]) <= high_rmse
        assert low_pcc <= float(values[3]) <= high_pcc


# --------------------------------------------------------------------------- polish (issue 13)


def _help(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as stop:
        main([*argv, "--help"])
    assert stop.value.code == 0
    return capsys.readouterr().out


def _verbs(group: click.Group, prefix: str = "") -> dict[str, click.Command]:
    """Every verb's command (``data synth`` ...), walked from the top."""
    found = {}
    for name, sub in group.commands.items():
        found[prefix + name] = sub
        if isinstance(sub, click.Group):
            found.update(_verbs(sub, f"{prefix}{name} "))
    return found


def test_every_option_has_help_and_shows_its_default(capsys):
    """Each option has its help, each argument is named in its verb's help, and a default
    is shown where there is one (not None or False)."""
    ours = _verbs(command())
    assert {"run", "demo", "sweep", "report", "pretrain", "data synth", "data check"} <= set(ours)
    assert {"deploy certs", "deploy supernode", "deploy run"} <= set(ours)
    silent = [
        f"{name} {p.name}"
        for name, verb in ours.items()
        for p in verb.params
        if isinstance(p, click.Option) and not p.hidden and not p.help
    ]
    assert silent == []
    unnamed = [
        f"{name} {word}"
        for name, verb in ours.items()
        for p in verb.params
        if isinstance(p, click.Argument)
        for word in p.metavar.strip("[].").split("|")
        if word not in verb.help
    ]
    assert unnamed == []
    out = _help(capsys, "demo")
    assert re.search(r"--scenes INTEGER +scenes to synthesise if absent +\[default: 1000\]", out)
    assert "[default: 0]" in out  # --seed: a default of 0 is shown too
    assert "[default: None]" not in out and "[default: False]" not in out
    assert "[default: 128]" in _help(capsys, "data", "check")


def test_run_print_config_resolves_like_a_run_and_runs_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # a config named relative to conf/, found from anywhere
    overrides = ["data.path=/data/x", "federated.rounds=7"]
    argv = ["run", "debug/fast.yaml", *overrides, "--print-config"]
    assert main([*argv, "--tracking-uri", "sqlite:///t.db"]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["federated"]["rounds"] == 7  # the override
    assert printed["tracking"]["uri"] == "sqlite:///t.db"  # the option
    expected = to_plain(load_config(CONF_DIR / "debug" / "fast.yaml", overrides))
    assert {**printed, "tracking": {**printed["tracking"], "uri": None}} == expected
    assert list(tmp_path.iterdir()) == []  # no store, no run
    assert main(["run", "no/such.yaml", "--print-config"]) == 1
    assert "no/such.yaml: config file not found" in capsys.readouterr().err


def test_sweep_help_lists_the_shipped_sweeps(capsys):
    out = _help(capsys, "sweep")
    listing = out[out.index("shipped sweeps") :]
    for path in SWEEPS_DIR.glob("*.yaml"):
        assert f"\n  {path.stem} " in listing
    assert "EWC lambda grid, FedAvg-EWC and FedRoot-EWC" in listing
    assert dict(shipped_sweeps())["paper_fl"] == "the paper's FL benchmark (Table I and III)"


def test_duration_reads_as_a_person_would():
    assert [duration(s) for s in (0.4, 42, 240, 3599, 4800)] == [
        "0 s",
        "42 s",
        "4 min",
        "1 h 00 min",
        "1 h 20 min",
    ]


def test_progress_off_a_terminal_logs_tenths_and_waits_between_lines(monkeypatch, capsys):
    clock = [0.0]
    monkeypatch.setattr(
        "fedlgr.shell.console.time", types.SimpleNamespace(monotonic=lambda: clock[0])
    )
    with Progress("decoding images", "img") as progress:
        assert progress.bar is None and not progress.terminal
        for done in range(1, 101):
            clock[0] = done * 0.5  # 100 images in 50 s
            progress(done, 100)
    lines = capsys.readouterr().err.splitlines()
    # A tenth at most every 10 s (every_s / 3): at 10, 20, ... seconds.
    assert lines[0] == "decoding images: 20/100 img (20%) after 10 s, about 40 s left"
    assert [line.split()[2] for line in lines] == [
        "20/100",
        "40/100",
        "60/100",
        "80/100",
        "100/100",
    ]
    assert lines[-1] == "decoding images: 100/100 img (100%) after 50 s"
    quiet = Progress("x", "it", enabled=False)
    quiet(1, 1)
    assert capsys.readouterr().err == ""


def test_default_threads_leave_busy_cores_alone(monkeypatch):
    import psutil

    from fedlgr.shell import machine as runtime

    def machine(cores, load, percent, machine_cores=None):
        """This process may use CPUs 0..cores-1 of machine_cores; load average; each CPU's
        use (%) over the sample."""
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)))
        monkeypatch.setattr(os, "cpu_count", lambda: machine_cores or cores)
        monkeypatch.setattr(os, "getloadavg", lambda: (load, 0.0, 0.0))
        monkeypatch.setattr(psutil, "cpu_percent", lambda interval, percpu: list(percent))

    machine(4, 0.2, [5, 0, 10, 0])
    assert (runtime.default_threads(), runtime.default_threads(2)) == (4, 2)  # idle: all
    machine(2, 3.8, [100, 100])  # the loaded 2-core VM of the issue
    assert runtime.default_threads() == 1
    machine(4, 2.6, [100, 60, 100, 0])
    assert runtime.busy_cores() == 2.6 and runtime.default_threads() == 1
    # The load average still holds this process's previous run; the sample finds idle cores.
    machine(2, 1.9, [3, 0])
    assert runtime.busy_cores() == pytest.approx(0.03) and runtime.default_threads() == 2
    # A 2-core cpuset on a 64-core machine: the machine's load scaled to its 2 cores (0.5);
    # the sample reads CPUs 0 and 1 only.
    machine(2, 16.0, [100, 100] + [0] * 62, machine_cores=64)
    assert runtime.busy_cores() == 0.5 and runtime.default_threads() == 2
    machine(8, 4.0, [100] * 4 + [0] * 4)
    assert runtime.default_threads(3) == 1  # 4 idle cores over 3 processes


def test_run_off_a_terminal_logs_progress_eta_and_threads(synth_dir, tmp_path, monkeypatch, capsys):
    """A fresh cache (images decoded), progress on, stderr not a terminal: log lines for
    the decoding and the client epochs; round lines with an ETA but the last; the header
    names the effective thread count and why it is below the cores."""
    from fedlgr.shell import machine as runtime
    from fedlgr.shell.run import experiment

    monkeypatch.setattr(Progress, "every_s", 0.0)  # a line for every step: the run is short
    monkeypatch.setattr(runtime, "available_cores", lambda: 4)
    monkeypatch.setattr(experiment, "available_cores", lambda: 4)
    monkeypatch.setattr(runtime, "busy_cores", lambda: 4.0)  # every core busy
    argv = [
        "run",
        str(FAST),
        f"data.path={synth_dir}",
        f"data.cache_dir={tmp_path / 'cache'}",
        "tracking.enabled=false",
        "runtime.progress=true",
        "runtime.threads=null",  # the default decides
        "federated.rounds=3",
        "data.modality=image",
        "data.clients=2",
        "train.epochs=2",
    ]
    assert main(argv) == 0
    captured = capsys.readouterr()
    out, err = captured.out.splitlines(), captured.err.splitlines()
    assert out[0].endswith(
        "36 training / 12 test scenes, "
        "1 torch thread (of 4 cores: the others are busy; runtime.threads to choose)"
    )
    rounds = [line for line in out if line.startswith("round ")]
    assert len(rounds) == 3
    assert re.search(r"\(\d+\.\d s, ETA \d+ s\)$", rounds[0]), rounds[0]
    assert re.search(r"\(\d+\.\d s\)$", rounds[2]), rounds[2]  # nothing left to wait for
    decoding = [line for line in err if line.startswith("decoding images: ")]
    assert decoding[-1].startswith("decoding images: 48/48 img (100%) after")
    # The bar counts each local epoch of each client: 2 clients x 2 epochs.
    training = "round 2/3, local training (2 clients x 2 epochs): "
    epochs = [line for line in err if line.startswith(training)]
    assert epochs[-1].startswith(f"{training}4/4 client-epochs (100%)")


def test_a_data_path_that_does_not_exist_is_named_before_torch_is_imported(tmp_path):
    """One line naming the setting and the folder, at once: not "file not found (expected
    the MANNERS-DB ratings CSV)" after torch's import (~11 s on 2 cores)."""
    missing = tmp_path / "no" / "such" / "dir"
    probe = (
        "import sys\n"
        "from fedlgr.shell.cli import main\n"
        f"code = main(['run', {str(FAST)!r}, 'data.path={missing}', 'tracking.enabled=false'])\n"
        "print('torch imported' if 'torch' in sys.modules else 'torch not imported')\n"
        "sys.exit(code)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 1, done.stderr[-3000:]
    assert done.stderr.strip() == (
        f"fedlgr: error: data.path={missing}: no such folder (give the dataset folder, the one "
        "holding the ratings CSV and images/; fedlgr data synth --out FOLDER writes one)"
    )
    assert done.stdout.strip() == "torch not imported"


def test_run_help_names_every_setting_group_and_the_page_that_documents_it(capsys):
    """Every section of the config (and federated.dp) is in ``fedlgr run --help``, each
    with a docs page that exists."""
    import dataclasses
    from pathlib import Path

    from fedlgr.shell.config import ExperimentConfig

    out = _help(capsys, "run")
    listed = out[out.index("settings, as key=value") :]
    assert "  method, seed  " in listed
    for f in dataclasses.fields(ExperimentConfig):
        if f.name not in ("method", "seed"):
            assert f"  {f.name}.*  " in listed, f.name
    assert "  federated.dp.*" in listed
    pages = set(re.findall(r"docs/\w+\.md", listed))
    assert pages and all((Path(__file__).parents[1] / p).is_file() for p in pages), pages


@pytest.mark.slow
def test_found_by_the_third_sweep_are_one_line_before_any_work(
    tmp_path, synth_dir, cache_dir, capsys, monkeypatch
):
    """A checkpoint folder that is a file, or lies under one (a read-only mount took the
    same path: a traceback from the owner's lock and a FAILED run), is refused before the
    MLflow run exists; `fedlgr data synth --size 100000` drew for minutes and ignored
    SIGTERM; `fedlgr report --out ''` filled the current folder with the report.
    A bad input of issue 20 (points 8 and 9)."""
    store = tmp_path / "mlflow.db"
    afile = tmp_path / "ckfile"
    afile.write_text("x")
    base = ["run", str(FAST), f"data.path={synth_dir}", "--tracking-uri", f"sqlite:///{store}"]
    assert main([*base, f"tracking.checkpoint_dir={afile}"]) == 1
    said = f"fedlgr: error: tracking.checkpoint_dir={afile}: a file, not a folder"
    assert capsys.readouterr().err.strip() == said
    assert main([*base, f"tracking.checkpoint_dir={afile / 'sub'}"]) == 1
    said = (
        f"fedlgr: error: tracking.checkpoint_dir={afile / 'sub'}: under {afile}, a file, "
        "not a folder"
    )
    assert capsys.readouterr().err.strip() == said
    client = mlflow.MlflowClient(f"sqlite:///{store}")
    assert not client.search_runs([e.experiment_id for e in client.search_experiments()])

    assert main(["data", "synth", "--out", str(tmp_path / "s"), "--size", "100000"]) == 1
    assert "size=100000: images are 16 to 4096 pixels wide" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()

    monkeypatch.chdir(tmp_path)
    before = sorted(tmp_path.iterdir())
    for out in ("", "."):
        assert main(["report", "--out", out, "--tracking-uri", f"sqlite:///{store}"]) == 1
        err = capsys.readouterr().err.strip()
        assert err == (
            "fedlgr: error: --out names the current folder ('' or .): name a folder of its "
            "own for the report's tables and plots (default: reports/NAME)"
        )
    assert sorted(tmp_path.iterdir()) == before


def test_data_show_refuses_its_bad_arguments_in_one_line(tmp_path, synth_dir, capsys):
    """Found by issue 20's fourth fault sweep."""
    cases = {
        "--scenes 0": (["--scenes", "0", "--out", str(tmp_path / "s.png")], "--scenes 0"),
        "--seed -1": (["--seed", "-1", "--out", str(tmp_path / "s.png")], "--seed -1"),
        "a folder": (["--out", str(tmp_path)], "name the picture file"),
        "a .txt": (["--out", str(tmp_path / "s.txt")], "ending in .png or .jpg or .jpeg"),
    }
    for case, (args, said) in cases.items():
        assert main(["data", "show", str(synth_dir), *args]) == 1, case
        [line] = capsys.readouterr().err.strip().splitlines()
        assert line.startswith("fedlgr: error: --") and said in line, case


def test_a_setting_given_twice_a_report_into_a_device_and_a_shared_store_are_refused(
    tmp_path, synth_dir, capsys
):
    """The tenth fault sweep: a setting given twice with two values kept the last and
    dropped the first without a word (d101, d145, d146), as did --tracking-uri with another
    tracking.uri= (d163); report --out /dev/null or a FIFO was "is a file" (d36, d37); a
    sweep whose base: is a FIFO "no such file" (d88); one sqlite file as --storage and
    tracking store failed after 11 s with Alembic's "No such revision" (d167)."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    run = ["run", "debug/tiny", f"data.path={synth_dir}"]
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    (tmp_path / "fifo_base.yaml").write_text(f"base: {fifo}\nspace:\n  seed: [1, 2]\n")
    (tmp_path / "grid.yaml").write_text("base: debug/tiny.yaml\nspace:\n  seed: [1, 2]\n")
    cases = {
        (*run, "seed=1", "seed=2", "--print-config"): (
            "command line: 'seed=1' and 'seed=2' both set seed; give one of them"
        ),
        (*run, f"data.path={tmp_path}", "--print-config"): (
            f"command line: 'data.path={synth_dir}' and 'data.path={tmp_path}' both set "
            "data.path; give one of them"
        ),
        (*run, "--tracking-uri", store, f"tracking.uri=sqlite:///{tmp_path / 'b.db'}"): (
            f"command line: --tracking-uri {store} and 'tracking.uri=sqlite:///"
            f"{tmp_path / 'b.db'}' name two tracking stores; give one of them"
        ),
        ("report", "--tracking-uri", store, "--out", "/dev/null"): (
            "/dev/null: is a device, pipe or socket; the report (--out) is a folder of tables "
            "and plots: name a new or existing folder"
        ),
        ("sweep", str(tmp_path / "fifo_base.yaml"), "--tracking-uri", store): (
            f"config {fifo}: {fifo} is not a regular file (a device, pipe or socket)"
        ),
        (
            *("sweep", str(tmp_path / "grid.yaml"), f"data.path={synth_dir}"),
            *("--tracking-uri", store, "--storage", store),
        ): (
            f"--storage {store}: the tracking store's file too; Optuna's study and MLflow's "
            f"runs each need a database of their own (e.g. --storage sqlite:///"
            f"{tmp_path / 'optuna.db'})"
        ),
    }
    for argv, said in cases.items():
        assert main(list(argv)) == 1, argv
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"fedlgr: error: {said}", argv
    assert main([*run, f"data.path={synth_dir}", "--print-config"]) == 0  # the same twice
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fifo", "fifo_base.yaml", "grid.yaml"]


@pytest.mark.slow
def test_one_value_spelled_twice_passes_and_what_a_sweep_would_drop_is_refused(
    tmp_path, synth_dir, cache_dir, capsys, monkeypatch
):
    """The eleventh fault sweep: one value spelled two ways (``seed=1 seed=01``, one sqlite
    file by two paths, ``tracking.uri=null``) was refused as two (e64, e73, d178); one
    sqlite file as --storage and store by a link or ``..`` was not caught (e81, e84); a
    sweep file's overrides: setting a key twice, or an override of a setting the space
    varies, were dropped without a word (e162, e163, e168); a config or sweep under a FIFO
    or a file was "not found" (e50, e147, e148); a tracking.checkpoint_dir of the user's
    named checkpoints was removed after the run (e92)."""
    monkeypatch.chdir(tmp_path)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    run = ["run", "debug/tiny", f"data.path={synth_dir}"]
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    for same in (
        ["seed=1", "seed=01"],
        ["tracking.uri=null", "--tracking-uri", store],
        ["tracking.uri=sqlite:///mlflow.db", "--tracking-uri", store],
    ):
        assert main([*run, *same, "--print-config"]) == 0, same
    capsys.readouterr()
    (tmp_path / "mlflow.db").touch()
    (tmp_path / "link.db").symlink_to(tmp_path / "mlflow.db")
    space = "space:\n  seed: [1, 2]\n"
    (tmp_path / "grid.yaml").write_text(f"base: debug/tiny.yaml\n{space}")
    (tmp_path / "twice.yaml").write_text(
        f"base: debug/tiny.yaml\noverrides: [seed=1, seed=2]\n{space}"
    )
    (tmp_path / "rounds.yaml").write_text(
        "base: debug/tiny.yaml\noverrides: [federated.rounds=1, federated.rounds=2]\n"
        "space:\n  train.lr_top: [0.1, 0.2]\n"
    )

    def sweep(name: str, *more: str) -> tuple[str, ...]:
        return ("sweep", name, f"data.path={synth_dir}", "--tracking-uri", store, *more)

    cases = {
        sweep("grid.yaml", "--storage", f"sqlite:///{tmp_path / 'link.db'}"): (
            f"--storage sqlite:///{tmp_path / 'link.db'}: the tracking store's file too; "
            "Optuna's study and MLflow's runs each need a database of their own (e.g. "
            f"--storage sqlite:///{tmp_path / 'optuna.db'})"
        ),
        sweep("grid.yaml", "seed=3"): (
            "sweep grid: 'seed=3' (the command line) sets seed, which its space: varies, "
            "each trial its own value; drop it, or take seed out of space:"
        ),
        sweep("rounds.yaml"): (
            "sweep rounds: its overrides: set federated.rounds twice ('federated.rounds=1', "
            "'federated.rounds=2'); keep one"
        ),
        sweep("twice.yaml"): (
            "sweep twice: 'seed=1' (its overrides:) sets seed, which its space: varies, each "
            "trial its own value; drop it, or take seed out of space:"
        ),
        ("run", f"{fifo}/x.yaml", "--print-config"): (
            f"{fifo}/x.yaml: under {fifo}, a device, pipe or socket, not a folder"
        ),
        ("sweep", f"{fifo}/s.yaml"): (
            f"sweep {fifo}/s.yaml: under {fifo}, a device, pipe or socket, not a folder"
        ),
    }
    for argv, said in cases.items():
        assert main(list(argv)) == 1, argv
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"fedlgr: error: {said}", argv
    mine = tmp_path / "mine" / "checkpoints"
    mine.mkdir(parents=True)
    base = [*run, f"data.cache_dir={cache_dir}", f"tracking.checkpoint_dir={mine}"]
    assert main([*base, "--tracking-uri", store]) == 0
    assert mine.is_dir() and not any(mine.iterdir())


@pytest.mark.slow
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_overrides_may_follow_options_and_stray_arguments_are_refused(
    synth_dir, cache_dir, tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    store = f"sqlite:///{tmp_path}/mlflow.db"
    args = [
        "run",
        str(FAST),
        f"data.cache_dir={cache_dir}",
        "--tracking-uri",
        store,
        "federated.rounds=2",
        f"data.path={synth_dir}",
        "runtime.threads=1",
    ]
    assert main(args) == 0, capsys.readouterr().err
    client, run = only_run(store)
    params = run.data.params
    assert params["federated.rounds"] == "2" and params["runtime.threads"] == "1"
    # Machine-local paths are not params (issue 13): the config artifact keeps them.
    assert "data.path" not in params and "tracking.uri" not in params
    config = client.download_artifacts(run.info.run_id, "config.yaml")
    assert f"path: {synth_dir}" in Path(config).read_text()
    assert metric_steps(client, run.info.run_id) == [1, 2]
    capsys.readouterr()

    for stray in ("--bogus", "stray"):
        with pytest.raises(SystemExit) as exit_:
            main([*args, stray])
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert re.search(rf"^fedlgr: error: unrecognized arguments: .*{stray}$", err, re.M), err
    assert len(experiment_runs(store)[1]) == 1  # nothing ran


@pytest.mark.usefixtures("telemetry_setting_restored")
def test_an_override_after_a_bare_resume_is_an_override():
    args = parse(["run", str(FAST), "--resume", "federated.rounds=2"])
    assert args.resume is True
    assert args.items == [str(FAST), "federated.rounds=2"]


@pytest.mark.usefixtures("telemetry_setting_restored")
def test_the_cli_turns_mlflow_telemetry_off_unless_the_user_chose(tmp_path, monkeypatch, capsys):
    missing = str(tmp_path / "missing.yaml")  # a verb that ends at once, with an error
    monkeypatch.delenv(TELEMETRY, raising=False)
    assert main(["run", missing]) == 1
    assert os.environ[TELEMETRY] == "true"
    monkeypatch.setenv(TELEMETRY, "false")
    assert main(["run", missing]) == 1
    assert os.environ[TELEMETRY] == "false"  # the user's explicit choice is kept
    assert capsys.readouterr().err.count("config file not found") == 2


SHOW_TELEMETRY = """
import atexit, os, runpy, sys

def show():
    client = sys.modules["mlflow.telemetry.client"].get_telemetry_client()
    print("TELEMETRY", os.environ.get("MLFLOW_DISABLE_TELEMETRY", "<unset>"), client)

atexit.register(show)
sys.argv = ["fedlgr", *sys.argv[1:]]
runpy.run_module("fedlgr", run_name="__main__", alter_sys=True)
"""


@pytest.mark.slow
@pytest.mark.parametrize(("given", "seen"), [(None, "true"), ("false", "false")])
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_a_fedlgr_process_runs_mlflow_without_telemetry_by_default(tmp_path, given, seen):
    """``python -m fedlgr report`` (it opens the store, then stops: no experiment) with
    the environment variable unset, and with a user's explicit ``false``."""
    env = child_env(**({TELEMETRY: given} if given else {}))
    store = f"sqlite:///{tmp_path}/empty.db"
    mlflow.MlflowClient(store).search_experiments()  # a store without fedlgr's experiment
    command = ["report", "--tracking-uri", store, "--no-log", "--out", str(tmp_path / "out")]
    done = subprocess.run(
        [sys.executable, "-c", SHOW_TELEMETRY, *command],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 1 and "fedlgr: error: no MLflow experiment" in done.stderr, (
        done.stderr
    )
    shown = [line for line in done.stdout.splitlines() if line.startswith("TELEMETRY ")]
    assert shown and shown[-1].split()[1] == seen, done.stdout
    if given is None:
        assert shown[-1] == "TELEMETRY true None"  # MLflow started no telemetry client
