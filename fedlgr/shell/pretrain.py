"""Pretrain a MobileNetV2 root offline to predict a scene's standardised descriptors and mode flags
from its image, on other data: the stand-in for the paper's ImageNet weights (``model.weights``)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from fedlgr.core.data.augment import Augment, SceneBatches
from fedlgr.core.data.scenes import Scenes
from fedlgr.core.models.scholar import MobileNetRoot
from fedlgr.shell.config import DataConfig
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.synth import synthesize


@dataclass(frozen=True)
class PretrainResult:
    path: Path
    images: int
    seconds: float
    first_loss: float
    last_loss: float  # mean standardised MSE over the last tenth of the steps


def pretrain_root(
    scenes: Scenes,
    out: Path | str,
    *,
    width: float = 1.0,
    images: int = 16000,
    batch_size: int = 32,
    lr: float = 1e-3,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> PretrainResult:
    """Train ``MobileNetRoot(width)`` + a linear head to predict ``scenes``' standardised features
    from ``images`` augmented images; save the root's state dict (keys ``root.*``, loadable with
    ``model.weights``)."""
    if scenes.images is None:
        raise ValueError("pretraining needs the image modality")
    torch.manual_seed(seed)
    features = scenes.features
    targets = (features - features.mean(0)) / features.std(0).clamp_min(1e-3)
    root = MobileNetRoot(width=width)
    model = nn.Sequential(root, nn.Linear(root.out_dim, targets.shape[1])).to(
        memory_format=torch.channels_last
    )
    optimizer = torch.optim.Adam(model.parameters(), lr=lr, fused=True)
    batches = SceneBatches(
        scenes.images,
        targets,
        np.arange(len(scenes)),
        min(batch_size, len(scenes)),  # drop_last must leave at least one batch
        augment=Augment(),
        seed=seed,
        drop_last=True,
    )
    start, seen, losses = time.perf_counter(), 0, []
    model.train()
    while seen < images:
        for x, y in batches:
            loss = nn.functional.mse_loss(model(x.contiguous(memory_format=torch.channels_last)), y)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            losses.append(loss.detach())
            seen += len(x)
            if progress is not None:
                progress(min(seen, images), images)
            if seen >= images:
                break
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    torch.save({f"root.{k}": v for k, v in root.state_dict().items()}, tmp)
    tmp.replace(out)
    tail = torch.stack(losses[-max(1, len(losses) // 10) :]).mean()
    return PretrainResult(out, seen, time.perf_counter() - start, float(losses[0]), float(tail))


PRETRAIN_SEED_OFFSET = 1000  # the pretraining scenes: another seed than the experiment's data


def synthetic_root(
    folder: Path | str,
    *,
    seed: int = 0,
    scenes: int = 2000,
    width: float = 0.5,
    images: int = 16000,
    size: int = 128,
    cache_dir: Path | None = None,
    progress: Callable[[str, str], AbstractContextManager] | None = None,
    echo=print,
) -> Path:
    """A root pretrained on ``scenes`` synthetic scenes of another seed than the experiments', made
    once in ``folder`` and reused. ``progress(desc, unit)``: a context manager giving each stage a
    ``(done, total)`` callback (e.g. :class:`fedlgr.shell.console.Progress`)."""
    folder = Path(folder)
    data = folder / f"synth-seed{seed + PRETRAIN_SEED_OFFSET}-{scenes}"
    path = folder / f"root-w{width:g}-{size}px-{scenes}scenes-{images}img-seed{seed}.pt"
    if path.is_file():
        return path
    stage = progress or (lambda desc, unit: contextlib.nullcontext(None))
    if not (data / "all_data.csv").is_file():
        with stage("synthesising", "scene") as bar:
            synthesize(data, scenes, seed + PRETRAIN_SEED_OFFSET, size, force=True, progress=bar)
    config = DataConfig(
        path=data, image_size=size, **({"cache_dir": cache_dir} if cache_dir else {})
    )
    echo(
        f"pretraining a width-{width:g} MobileNetV2 root on the descriptors of {data} "
        f"({images} images; once, then reused from {path})"
    )
    with stage("decoding images", "img") as bar:  # only when not cached yet
        table = load_scenes(config, progress=bar)
    with stage("pretraining", "img") as bar:
        result = pretrain_root(table, path, width=width, images=images, seed=seed, progress=bar)
    echo(
        f"pretrained in {result.seconds:.0f} s: descriptor MSE {result.first_loss:.2f} -> "
        f"{result.last_loss:.2f} (standardised)"
    )
    return path
