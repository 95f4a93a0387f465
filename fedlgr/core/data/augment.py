"""Training batches straight from the in-memory stores, with the paper's augmentation.

The paper's "W/ augmentation": each training scene appears ``copies`` (10) times per
epoch; each appearance is flipped horizontally with p=0.5 and rotated by an angle uniform
in [-10, 10] degrees with p=0.5; images are then scaled to 0..1 and normalised with the
ImageNet mean/std. A batch is one gather from the uint8 store, moved to the device as
uint8 (a quarter of the bytes of float32) and augmented there.

The descriptors (the features modality) are augmented as the LEAP-HRI'24 benchmark does
it (:class:`InputNoise`): ``copies`` rows per training scene with Gaussian noise on the 27
descriptors, drawn once for the client's scenes, so every epoch shows the same rows.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch.nn import functional as tnf
from torchvision.transforms.v2 import functional as F

from fedlgr.core.data.columns import DESCRIPTOR_COLUMNS

if TYPE_CHECKING:
    from fedlgr.core.settings import DataConfig

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def normalize(images: torch.Tensor) -> torch.Tensor:
    """uint8 (..., 3, H, W) -> float32 scaled to 0..1 and ImageNet-normalised."""
    return F.normalize(F.to_dtype(images, torch.float32, scale=True), IMAGENET_MEAN, IMAGENET_STD)


@lru_cache(maxsize=8)
def _base_grid(height: int, width: int, device: torch.device) -> torch.Tensor:
    # Pixel centres relative to the image centre, with a homogeneous 1: the grid that
    # torchvision's rotate builds (torchvision.transforms.v2.functional._geometry).
    xs = torch.linspace(-width * 0.5 + 0.5, width * 0.5 - 0.5, width, device=device)
    ys = torch.linspace(-height * 0.5 + 0.5, height * 0.5 - 0.5, height, device=device)
    grid = torch.ones(height, width, 3, device=device)
    grid[..., 0] = xs
    grid[..., 1] = ys[:, None]
    return grid.view(1, height * width, 3)


def rotate(images: torch.Tensor, degrees: torch.Tensor) -> torch.Tensor:
    """Rotate each float image ``images[b]`` by ``degrees[b]`` (counter-clockwise, about
    the centre, nearest neighbour, zero fill): ``v2.functional.rotate`` with one angle
    per image.

    torchvision's functional rotate takes one angle per call, and calling it per image
    cost ~0.4 ms each here; this builds the same sampling grid for all images at once and
    runs one ``grid_sample`` (~0.15 ms per image). ``tests/test_augment.py`` checks it
    against ``v2.functional.rotate`` pixel for pixel.
    """
    b, _, h, w = images.shape
    # The inverse rotation as torchvision builds it (_get_inverse_affine_matrix with -angle:
    # trigonometry in float64, then a 2x3 float matrix with zero translation), transposed
    # and scaled like its _affine_grid, so that nearest-neighbour ties fall the same way.
    rad = torch.deg2rad(degrees.to(images.device, torch.float64))
    cos, sin, zero = torch.cos(rad), torch.sin(rad), torch.zeros_like(rad)
    theta = torch.stack([torch.stack([cos, -sin, zero], 1), torch.stack([sin, cos, zero], 1)], 1)
    theta = theta.to(images.dtype).transpose(1, 2) / torch.tensor(
        [0.5 * w, 0.5 * h], device=images.device, dtype=images.dtype
    )  # (B, 3, 2)
    grid = _base_grid(h, w, images.device).expand(b, -1, -1).bmm(theta)
    return tnf.grid_sample(
        images, grid.view(b, h, w, 2), mode="nearest", padding_mode="zeros", align_corners=False
    )


class Augment:
    """Per-image random flip and rotation, drawn from an explicit generator."""

    def __init__(self, flip_p: float = 0.5, rotate_p: float = 0.5, max_degrees: float = 10.0):
        self.flip_p, self.rotate_p, self.max_degrees = flip_p, rotate_p, max_degrees

    def __call__(self, images: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """uint8 (B, 3, H, W) -> augmented, normalised float32 (B, 3, H, W)."""
        n = len(images)
        draws = torch.rand(3, n, generator=generator)  # flip?, rotate?, angle
        x = F.to_dtype(images, torch.float32, scale=True)
        # Touch only the chosen images: a masked select over the whole batch (torch.where)
        # cost ~10x more here.
        flip = torch.flatten(torch.nonzero(draws[0] < self.flip_p))
        if len(flip):
            flip = flip.to(x.device)
            x[flip] = F.horizontal_flip(x[flip])
        turn = torch.flatten(torch.nonzero(draws[1] < self.rotate_p))
        if len(turn):
            angles = (draws[2, turn] * 2 - 1) * self.max_degrees
            turn = turn.to(x.device)
            x[turn] = rotate(x[turn], angles)
        return F.normalize(x, IMAGENET_MEAN, IMAGENET_STD, inplace=True)


class InputNoise:
    """Noisy copies of each training scene's descriptors (Checker, Churamani & Gunes,
    LEAP-HRI'24; nchuramani/FCL-MannersDB): ``copies`` rows per scene, Gaussian noise of
    standard deviation ``std`` on its first ``columns`` inputs (the 27 descriptors; the
    mode flags after them stay as they are), drawn once. ``original``: the first copy is
    the scene itself (its FL notebooks: the scene and 8 noisy copies); ``cumulative``: copy
    k carries the sum of k draws, std x sqrt(k) (its code noised each copy in place on the
    row the previous copy had left: pandas before 3.0 hands out a row as a view;
    docs/leap_hri24.md)."""

    def __init__(
        self,
        std: float,
        columns: int = len(DESCRIPTOR_COLUMNS),
        original: bool = False,
        cumulative: bool = False,
    ):
        self.std, self.columns = std, columns
        self.original, self.cumulative = original, cumulative

    def draw(self, scenes: int, copies: int, width: int, generator: torch.Generator):
        """(copies x scenes, width) float32 noise, copy-major: row k is copy k // scenes of
        scene k % scenes (the order of ``positions.repeat(copies)``)."""
        noise = torch.zeros(copies, scenes, width)
        noisy = copies - 1 if self.original else copies
        draws = torch.randn(noisy, scenes, self.columns, generator=generator, dtype=torch.float64)
        draws = draws * self.std
        if self.cumulative:
            draws = draws.cumsum(dim=0)
        noise[copies - noisy :, :, : self.columns] = draws.float()
        return noise.reshape(copies * scenes, width)


def augmenter(data: DataConfig, images: bool) -> Augment | InputNoise | None:
    """``data.augment``'s augmentation for the modality: flips and rotations of images,
    noisy copies of the descriptors (``data.noise``); None when it is off."""
    if not data.augment:
        return None
    if images:
        return Augment()
    n = data.noise
    return InputNoise(n.std, len(DESCRIPTOR_COLUMNS), n.original, n.cumulative)


def _noise_seed(seed: int) -> int:
    """The noise's own seed: drawing it leaves the batches' generator (their order) as it is."""
    return int(np.random.SeedSequence([seed, 0x401CE]).generate_state(1)[0])


class SceneBatches:
    """Batches of (inputs, targets) over some scenes of the in-memory stores.

    Each ``iter()`` is one epoch: every position appears ``copies`` times, in an order
    drawn from the batches' own generator (so epochs differ and a seed repeats them).
    Image inputs (uint8) are normalised, and augmented if ``augment`` is given; feature
    inputs (float) pass through, each copy with its own noise if ``augment`` is an
    :class:`InputNoise` (drawn here, once, from ``seed``).
    """

    def __init__(
        self,
        inputs: torch.Tensor,
        targets: torch.Tensor,
        positions: np.ndarray,
        batch_size: int,
        *,
        shuffle: bool = True,
        copies: int = 1,
        augment: Augment | InputNoise | None = None,
        seed: int = 0,
        drop_last: bool = False,
        device: torch.device | str = "cpu",
    ):
        if batch_size < 1:
            raise ValueError(f"batch_size={batch_size}: must be >= 1")
        self.inputs, self.targets = inputs, targets
        self.positions = torch.as_tensor(np.asarray(positions), dtype=torch.long)
        self.batch_size, self.shuffle, self.copies = batch_size, shuffle, copies
        self.augment, self.drop_last = augment, drop_last
        self.device = torch.device(device)
        self.generator = torch.Generator().manual_seed(seed)
        self.images = inputs.dtype == torch.uint8
        self.noise = None  # (copies x positions, width): each copy's noise (InputNoise)
        if isinstance(augment, InputNoise) and not self.images:
            noise_rng = torch.Generator().manual_seed(_noise_seed(seed))
            self.noise = augment.draw(len(self.positions), copies, inputs.shape[1], noise_rng)

    @property
    def samples_per_epoch(self) -> int:
        return len(self.positions) * self.copies

    def __len__(self) -> int:
        n = self.samples_per_epoch
        return n // self.batch_size if self.drop_last else math.ceil(n / self.batch_size)

    def __iter__(self) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        slots = torch.arange(self.samples_per_epoch)  # copy-major: copy k // n of position k % n
        if self.shuffle:
            slots = torch.randperm(len(slots), generator=self.generator)
        order = self.positions.repeat(self.copies)[slots]
        for k in range(len(self)):
            cut = slice(k * self.batch_size, (k + 1) * self.batch_size)
            x, y = self.gather(order[cut])
            if self.noise is not None:
                x = x + self.noise[slots[cut]].to(x.device, non_blocking=True)
            yield x, y

    def peek(self) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """The first batch in position order, drawing nothing from the batches' generator."""
        yield self.gather(self.positions[: self.batch_size], torch.Generator().manual_seed(0))

    def gather(
        self, index: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The scenes at ``index`` (positions into the stores) as a training batch: on the
        device, normalised, and augmented (drawing from ``generator``, by default the
        batches' own) if these batches augment."""
        generator = self.generator if generator is None else generator
        index = torch.as_tensor(index, dtype=torch.long)
        x = self.inputs[index].to(self.device, non_blocking=True)
        y = self.targets[index].to(self.device, non_blocking=True)
        if self.images:
            x = self.augment(x, generator) if self.augment is not None else normalize(x)
        return x, y
