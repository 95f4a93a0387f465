"""load_scenes: a dataset folder as aligned per-scene tensors (fedlgr/shell/data/dataset.py)."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from fedlgr.core.data.columns import DESCRIPTOR_COLUMNS, LABEL_COLUMNS, MODE_COLUMNS, STAMP
from fedlgr.errors import DataError
from fedlgr.shell.config import DataConfig
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.images import decode


def csv_means(folder: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps (ascending), per-stamp mean labels (N, 8) and mean features (N, 29), from
    the CSV, recomputed with the csv module."""
    with (folder / "all_data.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows, "empty CSV"
    by_stamp: dict[int, list[dict[str, str]]] = {}
    for row in rows:
        by_stamp.setdefault(int(row[STAMP]), []).append(row)
    stamps = sorted(by_stamp)

    def mean(stamp: int, column: str) -> float:
        group = by_stamp[stamp]
        return sum(float(r[column]) for r in group) / len(group)

    labels = np.array([[mean(s, c) for c in LABEL_COLUMNS] for s in stamps])
    features = np.array(
        [[mean(s, c) for c in (*DESCRIPTOR_COLUMNS, *MODE_COLUMNS)] for s in stamps]
    )
    return np.array(stamps), labels, features


def close(tensor: torch.Tensor, array: np.ndarray) -> None:
    torch.testing.assert_close(
        tensor, torch.as_tensor(array, dtype=torch.float32), rtol=0, atol=1e-6
    )


@pytest.mark.parametrize("size", [24, 32])
def test_image_modality_tensors_match_the_files(synth_dir, cache_dir, size):
    scenes = load_scenes(DataConfig(path=synth_dir, image_size=size, cache_dir=cache_dir))
    stamps, labels, features = csv_means(synth_dir)
    assert len(scenes) == len(stamps) == 48
    assert np.array_equal(scenes.stamps, stamps)

    assert scenes.images.dtype == torch.uint8
    assert scenes.images.shape == (48, 3, size, size)
    assert scenes.targets.dtype == torch.float32 and scenes.targets.shape == (48, 8)
    assert scenes.features.dtype == torch.float32 and scenes.features.shape == (48, 29)
    close(scenes.targets, labels)
    close(scenes.features, features)
    # Features: the 27 descriptors, then the circle and arrow flags (exactly one set).
    assert torch.equal(scenes.features[:, 27] + scenes.features[:, 28], torch.ones(48))
    assert torch.equal(scenes.features[:, 27] == 1, torch.as_tensor(scenes.table.circle))
    assert scenes.targets.min() >= 1 and scenes.targets.max() <= 5
    assert scenes.inputs is scenes.images

    for i, stamp in enumerate(stamps.tolist()):
        expected = decode(synth_dir / "images" / f"{stamp}.png", size, None)
        assert torch.equal(scenes.images[i], expected), f"stamp {stamp}"
    # The images are not all the same picture.
    assert len(torch.unique(scenes.images.flatten(1), dim=0)) == 48


def test_second_load_comes_from_the_cache_and_is_identical(synth_dir, cache_dir):
    config = DataConfig(path=synth_dir, image_size=24, cache_dir=cache_dir)
    first = load_scenes(config)
    cached = list(cache_dir.glob("images-*.pt"))
    assert len(cached) == 1  # the given cache folder is the one used
    second = load_scenes(config)
    assert torch.equal(first.images, second.images)
    assert torch.equal(first.targets, second.targets)
    assert np.array_equal(first.stamps, second.stamps)
    assert list(cache_dir.glob("images-*.pt")) == cached


def test_features_modality_on_a_csv_only_folder(synth_copy, cache_dir):
    for path in synth_copy.iterdir():  # the images and the generator's synth.json
        if path.is_dir():
            shutil.rmtree(path)
        elif path.name != "all_data.csv":
            path.unlink()
    assert [p.name for p in synth_copy.iterdir()] == ["all_data.csv"]
    scenes = load_scenes(DataConfig(path=synth_copy, modality="features", cache_dir=cache_dir))
    stamps, labels, features = csv_means(synth_copy)
    assert scenes.images is None
    assert scenes.inputs is scenes.features
    assert np.array_equal(scenes.stamps, stamps)
    close(scenes.targets, labels)
    close(scenes.features, features)
    assert not cache_dir.exists() or not any(cache_dir.iterdir())  # nothing decoded

    with pytest.raises(DataError, match=r"data\.modality=features") as err:
        load_scenes(DataConfig(path=synth_copy, modality="image", cache_dir=cache_dir))
    assert str(synth_copy / "images") in str(err.value)


def test_subset_keeps_alignment(synth_dir, cache_dir):
    scenes = load_scenes(DataConfig(path=synth_dir, image_size=24, cache_dir=cache_dir))
    index = np.array([5, 0, 17, 3, 47])
    sub = scenes.subset(index)
    assert len(sub) == 5
    assert np.array_equal(sub.stamps, scenes.stamps[index])
    t = torch.as_tensor(index)
    assert torch.equal(sub.targets, scenes.targets[t])
    assert torch.equal(sub.features, scenes.features[t])
    assert torch.equal(sub.images, scenes.images[t])
    assert np.array_equal(sub.table.n_ratings, scenes.table.n_ratings[index])
    assert torch.equal(torch.as_tensor(sub.table.targets, dtype=torch.float32), sub.targets)
    # Positions from a split (int64 arrays) select the same way as a plain list would.
    again = scenes.subset(np.array([47, 47, 0], dtype=np.int64))
    assert np.array_equal(again.stamps, scenes.stamps[[47, 47, 0]])
    assert torch.equal(again.images, scenes.images[[47, 47, 0]])


def test_subset_with_a_boolean_mask_keeps_alignment(synth_dir, cache_dir):
    scenes = load_scenes(DataConfig(path=synth_dir, modality="features", cache_dir=cache_dir))
    mask = np.zeros(48, dtype=bool)
    mask[[3, 17]] = True
    sub = scenes.subset(mask)
    assert np.array_equal(sub.stamps, scenes.stamps[[3, 17]])
    assert torch.equal(sub.features, scenes.features[[3, 17]])


def test_subset_of_features_modality(synth_dir, cache_dir):
    scenes = load_scenes(DataConfig(path=synth_dir, modality="features", cache_dir=cache_dir))
    sub = scenes.subset(np.array([2, 4]))
    assert sub.images is None
    assert torch.equal(sub.features, scenes.features[[2, 4]])
    assert np.array_equal(sub.stamps, scenes.stamps[[2, 4]])


def test_skipped_images_drop_their_scenes_everywhere(synth_dir, synth_copy, cache_dir):
    full = load_scenes(DataConfig(path=synth_dir, image_size=24, cache_dir=cache_dir))
    missing, broken = int(full.stamps[10]), int(full.stamps[30])
    (synth_copy / "images" / f"{missing}.png").unlink()
    (synth_copy / "images" / f"{broken}.png").write_bytes(b"not a png at all")

    config = DataConfig(path=synth_copy, image_size=24, on_bad_image="skip", cache_dir=cache_dir)
    with pytest.warns(UserWarning) as record:
        scenes = load_scenes(config)
    messages = " | ".join(str(w.message) for w in record)
    assert f"{missing}" in messages and f"skipping stamp {broken}" in messages

    keep = ~np.isin(full.stamps, [missing, broken])
    assert len(scenes) == 46
    assert np.array_equal(scenes.stamps, full.stamps[keep])
    assert np.array_equal(scenes.table.stamps, scenes.stamps)
    k = torch.as_tensor(keep)
    assert scenes.images.shape == (46, 3, 24, 24)
    assert torch.equal(scenes.targets, full.targets[k])
    assert torch.equal(scenes.features, full.features[k])
    assert torch.equal(scenes.images, full.images[k])


def test_missing_image_is_an_error_by_default(synth_copy, cache_dir):
    (synth_copy / "images" / "260.png").unlink()
    with pytest.raises(DataError, match=r"no image for 1 stamp\(s\) of the CSV: 260"):
        load_scenes(DataConfig(path=synth_copy, image_size=24, cache_dir=cache_dir))


@pytest.mark.parametrize("name", ["notes.txt", "all_data.csv"])
def test_a_file_as_data_path_asks_for_the_folder(synth_copy, cache_dir, name, capsys):
    from fedlgr.shell.cli import main

    file = synth_copy / name
    if not file.exists():
        file.write_text("not a dataset\n")
    hint = f"; here data.path={synth_copy}" if name == "all_data.csv" else ""
    expected = (
        f"data.path={file} is a file; expected the dataset folder "
        f"(the one holding all_data.csv and images/{hint})"
    )
    for modality in ("image", "features"):
        with pytest.raises(DataError) as err:
            load_scenes(DataConfig(path=file, modality=modality, cache_dir=cache_dir))
        assert str(err.value) == expected
    assert main(["data", "check", str(file)]) == 1
    assert capsys.readouterr().err == f"fedlgr: error: {expected}\n"
