"""Readable summaries of a dataset: tables of its scenes and federated split, and
``fedlgr data show``'s contact sheet of a few scenes with their 8 mean labels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from fedlgr.core.data.columns import LABEL_SHORT_NAMES, LIKERT_MAX, LIKERT_MIN
from fedlgr.core.data.scenes import FederatedSplit, Scenes
from fedlgr.errors import ConfigError, DataError
from fedlgr.shell.console import table
from fedlgr.shell.data.images import IMAGE_SUFFIXES, Crop, decode, match_images
from fedlgr.shell.data.ratings import read_ratings

MAX_SCENES = 200  # one sheet: 200 tiles are already a picture of 896 x 18,700 px
TILE = 224
PANEL = 150
COLUMNS = 4


def describe_scenes(scenes: Scenes) -> str:
    t = scenes.table
    n_circle = int(t.circle.sum())
    head = (
        f"{t.source}: {len(t)} scenes from {int(t.n_ratings.sum())} ratings "
        f"({t.n_ratings.min()}-{t.n_ratings.max()} raters per scene), "
        f"{n_circle} circle / {len(t) - n_circle} arrow"
    )
    if scenes.images is not None:
        _, _, h, w = scenes.images.shape
        head += f", images {w}x{h}"
    targets = scenes.targets
    stats = (torch.mean, torch.std, torch.min, torch.max)
    rows = [
        (name, *(float(stat(targets[:, j])) for stat in stats))
        for j, name in enumerate(LABEL_SHORT_NAMES)
    ]
    return head + "\n\n" + table(["action", "mean", "sd", "min", "max"], rows)


def describe_split(split: FederatedSplit, most: int = 20) -> str:
    """One row per client and one for the shared test set; over ``most`` clients, the first
    ``most // 2`` rows and the scenes per client (min, median, max, clients with none)."""
    tasks = list(split.test_tasks)
    clients = split.clients
    shown = clients if len(clients) <= most else clients[: most // 2]
    rows = [(f"client {c.client}", len(c.train), *(len(c.tasks[k]) for k in tasks)) for c in shown]
    if len(shown) < len(clients):
        rows.append((f"({len(clients) - len(shown)} more clients)", *[""] * (1 + len(tasks))))
    rows.append(("test (shared)", len(split.test), *(len(split.test_tasks[k]) for k in tasks)))
    headers = ["shard", "scenes", *(f"task {k}" for k in tasks)]
    out = table(headers, rows)
    if len(shown) == len(clients):
        return out
    sizes = np.array([[len(c.train), *(len(c.tasks[k]) for k in tasks)] for c in clients])
    summary = [
        ("min", *sizes.min(axis=0)),
        ("median", *(f"{m:g}" for m in np.median(sizes, axis=0))),
        ("max", *sizes.max(axis=0)),
        ("clients with none", *(sizes == 0).sum(axis=0)),
    ]
    return f"{out}\n\nper client, over all {len(clients)} clients:\n" + table(
        ["", *headers[1:]], summary
    )


def _bar_colour(value: float) -> tuple[int, int, int]:
    """Red (1, inappropriate) through yellow to green (5, appropriate)."""
    t = (value - LIKERT_MIN) / (LIKERT_MAX - LIKERT_MIN)
    return (int(220 * min(1.0, 2 - 2 * t)), int(190 * min(1.0, 2 * t)), 40)


def contact_sheet(
    folder: Path | str, out: Path | str, n_scenes: int = 8, seed: int = 0, crop: Crop | None = None
) -> Path:
    """Write a PNG of ``n_scenes`` scenes (half circle, half arrow where possible), each
    annotated with its stamp, mode, number of raters and the 8 mean labels."""
    folder, out = Path(folder), Path(out)
    if not 1 <= n_scenes <= MAX_SCENES:
        raise ConfigError(f"--scenes {n_scenes}: a sheet shows 1 to {MAX_SCENES} scenes")
    if not 0 <= seed < 2**32:
        raise ConfigError(f"--seed {seed}: seeds are 0 to 2**32 - 1, as every fedlgr seed")
    if out.suffix.lower() not in IMAGE_SUFFIXES:
        raise ConfigError(
            f"--out {out}: name the picture file, ending in {' or '.join(IMAGE_SUFFIXES)}"
        )
    if out.is_dir():
        raise ConfigError(f"--out {out}: a folder; name the picture file ({out / 'sheet.png'})")
    table = read_ratings(folder)
    match = match_images(folder / "images", table.stamps)
    has_image = np.isin(table.stamps, list(match.files))
    if not has_image.any():
        raise DataError(f"{folder / 'images'}: no image matches a stamp of the CSV")
    rng = np.random.default_rng(seed)
    picks = []
    for mode in (table.circle, ~table.circle):  # alternate circle and arrow scenes
        pool = np.flatnonzero(has_image & mode)
        picks.append(rng.permutation(pool)[: (n_scenes + 1) // 2].tolist())
    chosen = [p for pair in zip(*picks, strict=False) for p in pair]
    chosen += [p for p in picks[0] + picks[1] if p not in chosen]
    chosen = chosen[:n_scenes]

    rows = (len(chosen) + COLUMNS - 1) // COLUMNS
    sheet = Image.new("RGB", (COLUMNS * TILE, rows * (TILE + PANEL)), "white")
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default(size=13)
    targets = table.targets
    for k, i in enumerate(chosen):
        x0, y0 = (k % COLUMNS) * TILE, (k // COLUMNS) * (TILE + PANEL)
        stamp = int(table.stamps[i])
        picture = decode(match.files[stamp], TILE - 8, crop).permute(1, 2, 0).numpy()
        sheet.paste(Image.fromarray(picture), (x0 + 4, y0 + 4))
        mode = "circle" if table.circle[i] else "arrow"
        caption = f"stamp {stamp} - {mode} - {table.n_ratings[i]} raters"
        draw.text((x0 + 6, y0 + TILE), caption, fill="black", font=font)
        for j, (name, value) in enumerate(zip(LABEL_SHORT_NAMES, targets[i], strict=True)):
            y = y0 + TILE + 17 + 15 * j
            draw.text((x0 + 6, y), name, fill="black", font=font)
            draw.text((x0 + 100, y), f"{value:.2f}", fill="black", font=font)
            width = int((TILE - 140) * (value - LIKERT_MIN) / (LIKERT_MAX - LIKERT_MIN))
            draw.rectangle(
                (x0 + 134, y + 3, x0 + 134 + max(width, 1), y + 12), fill=_bar_colour(value)
            )
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return out
