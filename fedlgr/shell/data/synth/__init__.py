"""A seeded synthetic living room in the exact MANNERS-DB layout (docs/data.md); each scene is
drawn from streams keyed by its index, so a larger set starts with the same scenes."""

from __future__ import annotations

import csv
import json
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fedlgr.core.data.columns import ALL_COLUMNS
from fedlgr.errors import ConfigError, DataError
from fedlgr.shell.checks.paths import not_a_folder
from fedlgr.shell.config import MAX_IMAGE_SIZE, MIN_IMAGE_SIZE
from fedlgr.shell.data.synth.appropriateness import RaterPool, true_appropriateness
from fedlgr.shell.data.synth.drawing import render
from fedlgr.shell.data.synth.layout import Layout, descriptors, sample_layout

FIRST_STAMP = 250
RATERS_PER_SCENE = (4, 6)
_SCENE_STREAM, _RATER_STREAM = 0, 1


@dataclass(frozen=True)
class SyntheticScene:
    stamp: int
    layout: Layout
    descriptors: np.ndarray  # (27,)
    truth: np.ndarray  # (8,) noiseless appropriateness
    ratings: np.ndarray  # (n_raters, 8) Likert 1..5

    @property
    def circle(self) -> bool:
        return self.layout.mode == "circle"


def generate_scenes(n_scenes: int, seed: int = 0) -> Iterator[SyntheticScene]:
    """Sample ``n_scenes`` scenes with their descriptors and ratings (no pictures)."""
    pool = RaterPool.sample(np.random.default_rng([seed, _RATER_STREAM]))
    for index in range(n_scenes):
        rng = np.random.default_rng([seed, _SCENE_STREAM, index])
        layout = sample_layout(rng)
        truth = true_appropriateness(layout)
        n_raters = int(rng.integers(RATERS_PER_SCENE[0], RATERS_PER_SCENE[1] + 1))
        raters = rng.choice(len(pool.bias), size=n_raters, replace=False)
        yield SyntheticScene(
            FIRST_STAMP + index, layout, descriptors(layout), truth, pool.rate(truth, raters, rng)
        )


def _rows(scene: SyntheticScene) -> Iterator[list[str]]:
    flags = ["1", "0"] if scene.circle else ["0", "1"]
    desc = [f"{v:.6f}" for v in scene.descriptors]
    for rating in scene.ratings:
        yield [str(scene.stamp), *flags, *desc, *(str(int(v)) for v in rating)]


@dataclass(frozen=True)
class SynthSummary:
    out: Path
    scenes: int
    ratings: int
    circle: int
    arrow: int
    label_means: np.ndarray
    seconds: float


MAX_SCENES = 1_000_000


def _prepare(out: Path, force: bool) -> None:
    csv_path, images = out / "all_data.csv", out / "images"
    if why := not_a_folder(out):  # a dangling link or a file is named as what it is
        raise DataError(f"{out}: {why}")
    if out.exists() and any(out.iterdir()):
        if not force:
            raise DataError(f"{out}: folder is not empty; pass --force to overwrite it")
        csv_path.unlink(missing_ok=True)
        shutil.rmtree(images, ignore_errors=True)
    try:
        images.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise DataError(f"{out}: cannot write there ({err.strerror or err})") from None


def synthesize(
    out: Path | str,
    scenes: int = 1000,
    seed: int = 0,
    size: int = 128,
    force: bool = False,
    progress=None,
) -> SynthSummary:
    """Write ``scenes`` synthetic scenes to ``out`` in the MANNERS-DB layout; ``progress``, if
    given, is called as ``progress(scenes_written, scenes)``."""
    if not 1 <= scenes <= MAX_SCENES:
        raise ConfigError(
            f"scenes={scenes}: 1 to {MAX_SCENES:,} scenes (MANNERS-DB has 1000; each scene is "
            "an image file)"
        )
    if not 0 <= seed < 2**32:
        raise ConfigError(f"seed={seed}: seeds are 0 to 2**32 - 1, as every fedlgr seed")
    if not MIN_IMAGE_SIZE <= size <= MAX_IMAGE_SIZE:
        raise ConfigError(
            f"size={size}: images are {MIN_IMAGE_SIZE} to {MAX_IMAGE_SIZE} pixels wide (as "
            "data.image_size; each scene is drawn at twice that first)"
        )
    if str(out) in ("", "."):
        raise ConfigError(
            "--out names the current folder ('' or .): name a folder of its own for the "
            "dataset (e.g. data/manners-synth)"
        )
    out = Path(out)
    start = time.perf_counter()
    made = not out.exists()
    _prepare(out, force)
    rows, n_circle, label_sum = [], 0, np.zeros(8)
    try:
        for k, scene in enumerate(generate_scenes(scenes, seed), start=1):
            # Pillow's PNG writer with fixed settings and no metadata is byte-stable.
            image = out / "images" / f"{scene.stamp}.png"
            render(scene.layout, size).save(image, compress_level=6)
            rows.extend(_rows(scene))
            n_circle += scene.circle
            label_sum += scene.ratings.mean(axis=0)
            if progress is not None:
                progress(k, scenes)
    except BaseException:  # Ctrl-C, SIGTERM, a full disk: no half dataset is left behind
        if made:
            shutil.rmtree(out, ignore_errors=True)
        else:  # --force: the old dataset is gone already; so is its description
            shutil.rmtree(out / "images", ignore_errors=True)
            for name in ("all_data.csv", "all_data.csv.tmp", "synth.json"):
                (out / name).unlink(missing_ok=True)
        raise
    tmp = out / "all_data.csv.tmp"
    with tmp.open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(ALL_COLUMNS)
        writer.writerows(rows)
    tmp.replace(out / "all_data.csv")
    meta = {"generator": "fedlgr.shell.data.synth", "scenes": scenes, "seed": seed, "size": size}
    (out / "synth.json").write_text(json.dumps(meta, indent=2) + "\n")
    return SynthSummary(
        out,
        scenes,
        len(rows),
        n_circle,
        scenes - n_circle,
        label_sum / scenes,
        time.perf_counter() - start,
    )
