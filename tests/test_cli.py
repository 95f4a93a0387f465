"""The command line: quick help, the data verbs and the interim demo."""

from __future__ import annotations

import subprocess
import sys

from PIL import Image

from fedlgr.cli import main


def test_help_does_not_import_heavy_modules():
    """``fedlgr --help`` stays fast because torch & co. load only inside the verbs."""
    code = (
        "import sys\n"
        "from fedlgr.cli import build_parser\n"
        "build_parser().format_help()\n"
        "heavy = [m for m in ('torch', 'torchvision', 'lightning', 'mlflow', 'optuna', 'numpy')"
        " if m in sys.modules]\n"
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


def test_impossible_split_names_the_setting(synth_dir, cache_dir, capsys):
    assert main(["data", "check", str(synth_dir), "--modality", "features", "--clients", "40"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("fedlgr: error: data.clients=40: more clients than the 36 training")


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
    assert "FedAvg-2c-aug: 1 rounds" in out and "FedRootAvg-2c-aug: 1 rounds" in out
    table = out[out.index("FedAvg vs FedRootAvg") :].splitlines()
    assert table[1].split()[:4] == ["method", "loss", "RMSE", "PCC"]
    assert table[3].startswith("FedAvg ") and table[4].startswith("FedRootAvg ")
    import mlflow

    client = mlflow.MlflowClient(store)
    runs = client.search_runs([client.get_experiment_by_name("demo").experiment_id])
    assert sorted(r.info.run_name for r in runs) == ["FedAvg-2c-aug", "FedRootAvg-2c-aug"]
    assert all(r.info.status == "FINISHED" for r in runs)
    csv_before = (data / "all_data.csv").read_bytes()
    assert main(args) == 0
    assert "synthesising" not in capsys.readouterr().out
    assert (data / "all_data.csv").read_bytes() == csv_before
