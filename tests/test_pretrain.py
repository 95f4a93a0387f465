"""The offline root pretraining and the FCL demo."""

from __future__ import annotations

import contextlib
import os

import mlflow
import pytest
import torch

from fedlgr.core.models.scholar import MobileNetRoot
from fedlgr.shell.cli import main
from fedlgr.shell.config import load_config
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.pretrain import pretrain_root, synthetic_root


def test_pretrained_root_loads_as_model_weights(synth_dir, cache_dir, tmp_path):
    scenes = load_scenes(
        load_config(
            None, [f"data.path={synth_dir}", "data.image_size=32", f"data.cache_dir={cache_dir}"]
        ).data
    )
    result = pretrain_root(scenes, tmp_path / "root.pt", width=0.1, images=96, batch_size=16)
    assert result.path.is_file() and result.images == 96
    assert torch.isfinite(torch.tensor([result.first_loss, result.last_loss])).all()
    saved = torch.load(result.path, weights_only=True)
    assert all(k.startswith("root.features.") for k in saved)
    root = MobileNetRoot(weights=str(result.path), width=0.1)
    assert torch.equal(root.features[0][0].weight, saved["root.features.0.0.weight"])


def test_synthetic_root_is_made_once_from_other_scenes(tmp_path, cache_dir):
    messages, reported = [], {}

    @contextlib.contextmanager
    def stage(desc: str, unit: str):  # what the demo's Progress bars are given
        yield lambda done, total: reported.setdefault((desc, unit), []).append((done, total))

    settings = dict(seed=3, scenes=24, width=0.1, images=32, size=32, cache_dir=cache_dir)
    path = synthetic_root(tmp_path, **settings, echo=messages.append, progress=stage)
    assert path.is_file() and (tmp_path / "synth-seed1003-24" / "all_data.csv").is_file()
    assert any("pretraining a width-0.1 MobileNetV2 root" in m for m in messages)
    # Every stage reports, up to its end: 24 scenes written and decoded, 32 images trained.
    ends = {stage: calls[-1] for stage, calls in reported.items()}
    assert ends == {
        ("synthesising", "scene"): (24, 24),
        ("decoding images", "img"): (24, 24),
        ("pretraining", "img"): (32, 32),
    }
    stamp = os.stat(path).st_mtime_ns
    again = synthetic_root(tmp_path, **settings, echo=messages.append)
    assert again == path and os.stat(path).st_mtime_ns == stamp and len(messages) == 2


def test_pretrain_command(synth_dir, tmp_path, cache_dir, capsys):
    out = tmp_path / "r.pt"
    assert (
        main(
            [
                "pretrain",
                "--data",
                str(synth_dir),
                "--out",
                str(out),
                "--width",
                "0.1",
                "--images",
                "32",
                "--size",
                "32",
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert (
        text.startswith(f"wrote {out}: 32 images")
        and f"model.weights={out} model.width=0.1" in text
    )


@pytest.mark.slow
def test_fcl_demo_compares_fedroot_without_cl_and_fedlgr(tmp_path, cache_dir, capsys):
    store = f"sqlite:///{tmp_path}/mlflow.db"
    fast = [
        "continual.rounds_per_task=1",
        "train.max_batches=2",
        "train.epochs=1",
        "data.image_size=32",
        "model.width=0.1",
        "continual.lgr.epochs=2",
        f"data.cache_dir={cache_dir}",
        "runtime.progress=false",
    ]
    args = [
        "demo",
        "--fcl",
        "--modality",
        "image",
        "--data",
        str(tmp_path / "synth"),
        "--scenes",
        "32",
        "--pretrain-scenes",
        "24",
        "--pretrain-images",
        "32",
        "--tracking-uri",
        store,
        *fast,
    ]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "FedRoot-FT-2c-noaug-image: 2 tasks (circle, arrow)" in out and "FedLGR-2c-noaug" in out
    table = out[out.index("Forgetting on") :].splitlines()
    assert table[1].split()[:3] == ["method", "circle", "RMSE"]
    assert table[3].startswith("FedRoot-FT ") and table[4].startswith("FedLGR ")
    client = mlflow.MlflowClient(store)
    runs = client.search_runs([client.get_experiment_by_name("demo-fcl").experiment_id])
    assert sorted(r.data.tags["method"] for r in runs) == ["FedLGR", "FedRoot-FT"]
    for r in runs:
        assert r.data.params["model.weights"].endswith(".pt")  # from the pretrained root
        assert "after_task2/forgetting/circle/rmse" in r.data.metrics


@pytest.mark.slow
def test_fcl_demo_on_the_descriptors_needs_no_pretrained_root(tmp_path, capsys):
    store = f"sqlite:///{tmp_path}/mlflow.db"
    data = tmp_path / "synth"
    args = ["demo", "--fcl", "--data", str(data), "--scenes", "48", "--tracking-uri", store]
    fast = ["continual.rounds_per_task=2", "train.epochs=1", "continual.lgr.epochs=3"]
    assert main([*args, *fast, "runtime.progress=false"]) == 0
    out = capsys.readouterr().out
    assert f"Forgetting on {data} (features)" in out and "pretraining" not in out
    assert not (tmp_path / "pretrain").exists()
    client = mlflow.MlflowClient(store)
    runs = client.search_runs([client.get_experiment_by_name("demo-fcl").experiment_id])
    assert sorted(r.data.tags["method"] for r in runs) == ["FedLGR", "FedRoot-FT"]
    for r in runs:
        assert r.data.params["data.modality"] == "features"
        assert r.data.params["model.root"] == "mlp"
        assert r.data.params["continual.rounds_per_task"] == "2"  # the user's setting wins
        assert "after_task2/forgetting/circle/rmse" in r.data.metrics
