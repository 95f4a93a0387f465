"""The synthetic living room: determinism, layout, descriptors and the label rules."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from fedlgr.core.data.columns import ALL_COLUMNS, DESCRIPTOR_COLUMNS
from fedlgr.errors import ConfigError, DataError
from fedlgr.shell.cli import main
from fedlgr.shell.data.ratings import read_ratings
from fedlgr.shell.data.synth import MAX_SCENES, generate_scenes, synthesize
from fedlgr.shell.data.synth.appropriateness import true_appropriateness
from fedlgr.shell.data.synth.layout import Layout, Person, descriptors
from tests.support.data import read_rows


def _files(folder):
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_same_seed_is_byte_identical_and_another_seed_differs(tmp_path):
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        assert (
            main(
                [
                    "data",
                    "synth",
                    "--out",
                    str(tmp_path / name),
                    "--scenes",
                    "12",
                    "--seed",
                    str(seed),
                    "--size",
                    "24",
                ]
            )
            == 0
        )
    a, b, c = (_files(tmp_path / n) for n in "abc")
    assert len(a) == 12 + 2  # 12 images, all_data.csv, synth.json
    assert a == b
    assert (
        a[next(iter(p for p in a if p.name == "all_data.csv"))]
        != c[next(iter(p for p in c if p.name == "all_data.csv"))]
    )
    differing = [p for p in a if p.suffix == ".png" and a[p] != c[p]]
    assert len(differing) == 12


def test_layout_matches_manners_db(synth_dir):
    rows = read_rows(synth_dir / "all_data.csv")
    assert rows[0] == list(ALL_COLUMNS)
    assert len(rows[0]) == 38
    stamps = sorted({int(r[0]) for r in rows[1:]})
    assert stamps == list(range(250, 250 + 48))
    images = sorted((synth_dir / "images").iterdir())
    assert [p.name for p in images] == [f"{s}.png" for s in stamps]
    assert Image.open(images[0]).size == (32, 32)
    assert Image.open(images[0]).mode == "RGB"
    for r in rows[1:]:
        assert r[1:3] in (["1", "0"], ["0", "1"])
        assert all(0.0 <= float(v) <= 1.0 for v in r[3:30])
        assert all(v in {"1", "2", "3", "4", "5"} for v in r[30:])


def test_csv_holds_the_generated_scenes(synth_dir):
    table = read_ratings(synth_dir)
    scenes = list(generate_scenes(48, seed=7))
    assert table.stamps.tolist() == [s.stamp for s in scenes]
    desc = np.stack([table.values[c] for c in DESCRIPTOR_COLUMNS], axis=1)
    np.testing.assert_allclose(desc, np.stack([s.descriptors for s in scenes]), atol=1e-6)
    np.testing.assert_allclose(table.targets, np.stack([s.ratings.mean(0) for s in scenes]))
    assert table.n_ratings.tolist() == [len(s.ratings) for s in scenes]
    assert table.circle.tolist() == [s.circle for s in scenes]


def test_a_smaller_set_is_a_prefix_of_a_larger_one():
    small = list(generate_scenes(5, seed=1))
    large = list(generate_scenes(9, seed=1))
    for a, b in zip(small, large, strict=False):
        assert a.layout == b.layout
        np.testing.assert_array_equal(a.ratings, b.ratings)


def test_refuses_to_overwrite_without_force(tmp_path):
    synthesize(tmp_path / "d", scenes=3, size=16)
    with pytest.raises(DataError, match="not empty; pass --force"):
        synthesize(tmp_path / "d", scenes=3, size=16)
    (tmp_path / "d" / "images" / "999.png").write_bytes(b"stale")
    synthesize(tmp_path / "d", scenes=2, size=16, force=True)
    assert sorted(p.name for p in (tmp_path / "d" / "images").iterdir()) == ["250.png", "251.png"]


def _room(mode: str, people=(), heading=0.0, zone=0.3) -> Layout:
    return Layout(
        robot_x=0.5,
        robot_y=0.5,
        robot_heading=heading,
        mode=mode,
        zone=zone,
        sofa=(0.1, 0.04, 0.42, 0.15),
        sofa_side="top",
        table=(0.7, 0.7, 0.86, 0.8),
        speaker=(0.92, 0.92),
        music=False,
        people=tuple(people),
    )


def test_descriptors_of_a_hand_made_room():
    # One adult 0.24 straight ahead of the robot (heading +x), facing the robot.
    d = dict(
        zip(
            DESCRIPTOR_COLUMNS,
            descriptors(_room("circle", [Person(0.74, 0.5, math.pi)])),
            strict=True,
        )
    )
    assert d["Number of people"] == pytest.approx(0.1)
    assert d["Distance to closest human"] == pytest.approx(0.24 / 1.2)
    assert d["Direction to closest human"] == pytest.approx(0.0)
    assert d["Robot facing closest human?"] == 1.0
    assert d["Closest human facing robot?"] == 1.0
    assert d["Direction from closest human to robot"] == pytest.approx(0.0)
    assert d["Distance to 2nd closest human"] == 1.0  # absent reads as far away
    assert d["2nd closest human facing robot?"] == 0.0
    assert d["Robot work radius"] == pytest.approx(0.3 / 0.5)
    assert d["Number of agents in scene"] == pytest.approx(2 / 13)
    # Behind the robot and looking away.
    d = dict(
        zip(
            DESCRIPTOR_COLUMNS,
            descriptors(_room("circle", [Person(0.3, 0.5, math.pi)])),
            strict=True,
        )
    )
    assert d["Direction to closest human"] == pytest.approx(1.0)
    assert d["Robot facing closest human?"] == 0.0
    assert d["Closest human facing robot?"] == 0.0


def test_circle_and_arrow_read_the_room_differently():
    child_ahead = Person(0.66, 0.5, 0.0, child=True)  # in front, back turned to the robot
    child_behind = Person(0.34, 0.5, math.pi, child=True)  # equally close, behind
    vacuum = 0
    circle = [
        true_appropriateness(_room("circle", people))[vacuum]
        for people in ([], [child_ahead], [child_behind])
    ]
    arrow = [
        true_appropriateness(_room("arrow", people))[vacuum]
        for people in ([], [child_ahead], [child_behind])
    ]
    assert circle[1] == pytest.approx(circle[2])  # a circle is a circle, all around
    assert circle[1] < circle[0] - 1.0
    assert arrow[2] - arrow[1] > 2.0  # in the path it matters; behind it hardly does
    assert arrow[0] - arrow[2] < 0.6  # (only the room-wide effects of a child nearby)
    assert arrow[1] < circle[1] - 1.0  # unaware and in the path: worse than in a circle


def _linear_fit(x, y):
    a = np.c_[x, np.ones(len(x))]
    return np.linalg.lstsq(a, y, rcond=None)[0]


def _scores(w, x, y):
    pred = np.c_[x, np.ones(len(x))] @ w
    pcc = np.mean([np.corrcoef(pred[:, k], y[:, k])[0, 1] for k in range(y.shape[1])])
    rmse = np.mean(np.sqrt(((pred - y) ** 2).mean(axis=0)))
    return pcc, rmse


@pytest.mark.slow
def test_labels_are_learnable_and_the_modes_obey_different_rules(tmp_path):
    # Through the written CSV and the reader: the path real data takes.
    synthesize(tmp_path / "d", scenes=1600, seed=11, size=16)
    table = read_ratings(tmp_path / "d")
    x = np.stack([table.values[c] for c in DESCRIPTOR_COLUMNS], axis=1)
    y = table.targets
    circle, arrow = np.flatnonzero(table.circle), np.flatnonzero(~table.circle)
    c_train, c_test = circle[: len(circle) * 3 // 4], circle[len(circle) * 3 // 4 :]
    a_train, a_test = arrow[: len(arrow) * 3 // 4], arrow[len(arrow) * 3 // 4 :]

    w_circle = _linear_fit(x[c_train], y[c_train])
    pcc_cc, rmse_cc = _scores(w_circle, x[c_test], y[c_test])
    pcc_ca, rmse_ca = _scores(w_circle, x[a_test], y[a_test])
    pcc_aa, _ = _scores(_linear_fit(x[a_train], y[a_train]), x[a_test], y[a_test])

    assert pcc_cc >= 0.5 and pcc_aa >= 0.5  # learnable within a mode
    assert rmse_ca >= 1.5 * rmse_cc  # the circle rule does markedly worse on arrow scenes
    assert pcc_ca <= pcc_cc - 0.1


def test_synthetic_data_goes_to_a_folder_of_its_own_that_can_be_written(
    tmp_path, capsys, monkeypatch
):
    """Found by the re-test: `data synth` to a read-only place was a traceback, and
    `--out ''` wrote the dataset into the current folder.
    A bad input of issue 20 (points 8 and 9)."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert main(["data", "synth", "--out", str(afile / "s"), "--scenes", "1", "--size", "16"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"fedlgr: error: {afile / 's'}: under {afile}, a file, not a folder"
    monkeypatch.chdir(tmp_path)
    for out in ("", "."):
        assert main(["data", "synth", "--out", out, "--scenes", "1", "--size", "16"]) == 1
        assert "--out names the current folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_synth_refuses_a_seed_and_a_count_out_of_range_before_writing(tmp_path):
    """Found by issue 20's fourth fault sweep."""
    for seed in (-1, 2**32):
        with pytest.raises(ConfigError, match=f"seed={seed}: seeds are 0 to 2\\*\\*32 - 1"):
            synthesize(tmp_path / "out", scenes=4, seed=seed, size=32)
    with pytest.raises(ConfigError, match="scenes=1000001: 1 to 1,000,000 scenes"):
        synthesize(tmp_path / "out", scenes=MAX_SCENES + 1, size=32)
    assert not (tmp_path / "out").exists()
    assert main(["data", "synth", "--out", str(tmp_path / "cli"), "--seed", "-1"]) == 1
    assert not (tmp_path / "cli").exists()


def test_an_interrupted_synth_leaves_no_half_dataset(tmp_path):
    """Found by issue 20's fourth fault sweep."""

    def interrupt(done, total):
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        synthesize(tmp_path / "new", scenes=8, size=32, progress=interrupt)
    assert not (tmp_path / "new").exists()  # made by this call: removed
    kept = tmp_path / "kept"
    synthesize(kept, scenes=4, size=32)
    with pytest.raises(KeyboardInterrupt):
        synthesize(kept, scenes=8, size=32, force=True, progress=interrupt)
    assert not any(kept.iterdir())  # the old dataset went with --force; nothing half-made
