"""Batched rotation, per-image augmentation and epoch batches (fedlgr/core/data/augment.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torchvision.transforms.v2 import functional as F

from fedlgr.core.data.augment import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    Augment,
    InputNoise,
    SceneBatches,
    augmenter,
    normalize,
    rotate,
)

ANGLES = [0.0, 5.0, -7.5, 10.0, -10.0, 3.3, -0.6, 33.25, 90.0]


def random_uint8(n: int, height: int = 32, width: int = 32, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, 3, height, width), dtype=torch.uint8, generator=g)


def asymmetric_image(size: int = 32) -> torch.Tensor:
    """A uint8 (3, S, S) image, no pixel black, that differs from its mirror image."""
    ramp = torch.arange(size * size, dtype=torch.int64).view(size, size)
    channels = [ramp % 251, (ramp * 7) % 253, (ramp // size) * 5 % 250]
    image = (torch.stack(channels) + 1).to(torch.uint8)
    assert not torch.equal(image, F.horizontal_flip(image))
    return image


def g(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# --- rotate ------------------------------------------------------------------------------


@pytest.mark.parametrize(("height", "width"), [(32, 32), (37, 53), (53, 37)])
def test_rotate_matches_torchvision_pixel_for_pixel(height, width):
    x = F.to_dtype(random_uint8(len(ANGLES), height, width), torch.float32, scale=True)
    angles = torch.tensor(ANGLES)
    out = rotate(x, angles)
    assert out.shape == x.shape and out.dtype == torch.float32
    for i, angle in enumerate(angles.tolist()):
        expected = F.rotate(x[i : i + 1], angle)  # NEAREST, fill 0, about the centre
        assert torch.equal(out[i : i + 1], expected), f"angle {angle}"


def test_rotate_batch_equals_one_by_one():
    x = F.to_dtype(random_uint8(6, 24, 24, seed=1), torch.float32, scale=True)
    angles = torch.tensor([-9.9, -3.0, 0.0, 1.5, 7.25, 9.75])
    batch = rotate(x, angles)
    for i in range(len(x)):
        assert torch.equal(batch[i : i + 1], rotate(x[i : i + 1], angles[i : i + 1]))


def test_rotate_zero_is_identity_and_ninety_is_rot90():
    x = F.to_dtype(random_uint8(2, 16, 16, seed=2), torch.float32, scale=True)
    assert torch.equal(rotate(x, torch.zeros(2)), x)
    # Counter-clockwise: the top row ends up as the left column, read bottom to top.
    assert torch.equal(rotate(x, torch.full((2,), 90.0)), torch.rot90(x, 1, dims=(2, 3)))


def test_rotate_at_128_px_matches_torchvision_exactly():
    """At 128 px some angles put a sampling point on a nearest-neighbour tie; computing the
    trigonometry in float64, as torchvision does, makes both pick the same neighbour."""
    x = F.to_dtype(random_uint8(40, 128, 128, seed=3), torch.float32, scale=True)
    angles = torch.cat(
        [(torch.rand(38, generator=g(3)) * 2 - 1) * 10, torch.tensor([-9.76049, -5.89637])]
    )
    out = rotate(x, angles)
    for i in range(len(x)):
        assert torch.equal(out[i], F.rotate(x[i : i + 1], angles[i].item())[0]), angles[i]


# --- normalize / Augment -----------------------------------------------------------------


def test_normalize_maps_0_and_255_to_the_imagenet_extremes():
    images = torch.zeros(2, 3, 4, 5, dtype=torch.uint8)
    images[1] = 255
    out = normalize(images)
    assert out.dtype == torch.float32 and out.shape == images.shape
    for c in range(3):
        low = torch.full((4, 5), -IMAGENET_MEAN[c] / IMAGENET_STD[c])
        high = torch.full((4, 5), (1 - IMAGENET_MEAN[c]) / IMAGENET_STD[c])
        torch.testing.assert_close(out[0, c], low)
        torch.testing.assert_close(out[1, c], high)


def test_normalize_of_a_middle_value():
    images = torch.full((1, 3, 2, 2), 51, dtype=torch.uint8)  # 51 / 255 = 0.2
    out = normalize(images)
    for c in range(3):
        expected = (0.2 - IMAGENET_MEAN[c]) / IMAGENET_STD[c]
        assert out[0, c].sub(expected).abs().max() < 1e-6


def test_augment_always_flip_never_rotate_is_a_flip():
    x = random_uint8(5, 20, 28, seed=4)
    out = Augment(flip_p=1.0, rotate_p=0.0)(x, g(0))
    assert out.dtype == torch.float32
    assert torch.equal(out, normalize(F.horizontal_flip(x)))
    assert not torch.equal(out, normalize(x))


def test_augment_never_flip_never_rotate_is_normalize():
    x = random_uint8(5, seed=5)
    assert torch.equal(Augment(0.0, 0.0)(x, g(1)), normalize(x))


def test_augment_does_not_change_its_input():
    x = random_uint8(8, seed=6)
    before = x.clone()
    Augment(1.0, 1.0)(x, g(2))
    assert torch.equal(x, before)


def test_augment_draws_per_image():
    batch = asymmetric_image().expand(64, -1, -1, -1).contiguous()
    out = Augment()(batch, g(0))
    assert out.shape == (64, 3, 32, 32) and out.dtype == torch.float32
    distinct = torch.unique(out.flatten(1), dim=0)
    assert len(distinct) >= 10  # flips and rotations by different angles
    plain = normalize(batch[:1])
    assert (out == plain).flatten(1).all(1).any()  # some images are left as they are


def test_fraction_flipped_is_about_half():
    n = 500
    image = asymmetric_image()
    batch = image.expand(n, -1, -1, -1).contiguous()
    out = Augment(flip_p=0.5, rotate_p=0.0)(batch, g(11))
    plain, flipped = normalize(image), normalize(F.horizontal_flip(image))
    is_plain = (out == plain).flatten(1).all(1)
    is_flipped = (out == flipped).flatten(1).all(1)
    assert bool((is_plain ^ is_flipped).all())  # each output is exactly one of the two
    assert 0.4 <= is_flipped.float().mean().item() <= 0.6


def test_fraction_rotated_is_about_half():
    n = 500
    image = asymmetric_image(48)
    batch = image.expand(n, -1, -1, -1).contiguous()
    out = Augment(flip_p=0.0, rotate_p=0.5)(batch, g(12))
    plain = normalize(image)
    changed = ~(out == plain).flatten(1).all(1)
    # A rotation by a tiny angle may leave a nearest-neighbour image as it was, so this
    # slightly undercounts the rotated images.
    assert 0.4 <= changed.float().mean().item() <= 0.6
    # Rotated images have zero-filled (normalised 0) corners; plain ones keep the corner.
    zero = normalize(torch.zeros(1, 3, 1, 1, dtype=torch.uint8))[0, :, 0, 0]
    corners_zero = (out[:, :, 0, 0] == zero).all(1)
    assert corners_zero.float().mean().item() > 0.35
    assert torch.equal(corners_zero, corners_zero & changed)


def test_augment_replays_its_draws():
    """White-box: draws are rand(3, n) = (flip?, rotate?, angle), angle in [-max, max]."""
    x = random_uint8(40, 24, 24, seed=7)
    out = Augment(0.5, 0.5, max_degrees=10.0)(x, g(21))
    flip_u, turn_u, angle_u = torch.rand(3, 40, generator=g(21))
    assert (turn_u < 0.5).any() and (flip_u < 0.5).any()
    for i in range(40):
        expected = F.to_dtype(x[i : i + 1], torch.float32, scale=True)
        if flip_u[i] < 0.5:
            expected = F.horizontal_flip(expected)
        if turn_u[i] < 0.5:
            angle = (angle_u[i] * 2 - 1) * 10.0
            assert -10.0 <= angle <= 10.0
            expected = F.rotate(expected, angle.item())
        expected = F.normalize(expected, IMAGENET_MEAN, IMAGENET_STD)
        assert torch.equal(out[i : i + 1], expected), f"image {i}"


def test_augment_same_seed_same_batch_other_seed_other_batch():
    x = random_uint8(32, seed=8)
    aug = Augment()
    a, b, c = aug(x, g(3)), aug(x, g(3)), aug(x, g(4))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    # One generator carries on: its next batch differs from its first.
    gen = g(3)
    first, second = aug(x, gen), aug(x, gen)
    assert torch.equal(first, a) and not torch.equal(first, second)


# --- SceneBatches ------------------------------------------------------------------------

POSITIONS = np.array([1, 3, 4, 7, 9])


def feature_store(n: int = 12) -> tuple[torch.Tensor, torch.Tensor]:
    """Features whose row i is (4i, 4i+1, 4i+2, 4i+3) + 0.5; targets (i, i*i) as floats."""
    inputs = torch.arange(n * 4, dtype=torch.float32).view(n, 4) + 0.5
    rows = torch.arange(n, dtype=torch.float32)
    return inputs, torch.stack([rows, rows * rows], 1)


def row_of(x: torch.Tensor) -> torch.Tensor:
    return ((x[:, 0] - 0.5) / 4).long()


def epoch(batches: SceneBatches) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
    xs, ys, sizes = [], [], []
    for x, y in batches:
        xs.append(x)
        ys.append(y)
        sizes.append(len(x))
    return torch.cat(xs), torch.cat(ys), sizes


def test_every_position_appears_copies_times_per_epoch():
    inputs, targets = feature_store()
    batches = SceneBatches(inputs, targets, POSITIONS, batch_size=7, copies=10, seed=0)
    assert batches.samples_per_epoch == 50
    assert len(batches) == math.ceil(50 / 7) == 8
    x, _, sizes = epoch(batches)
    assert sizes == [7] * 7 + [1]
    rows = row_of(x)
    counts = torch.bincount(rows, minlength=12)
    assert counts[POSITIONS].tolist() == [10] * 5
    assert counts.sum().item() == 50  # nothing outside the positions


def test_feature_inputs_pass_through_and_targets_align():
    inputs, targets = feature_store()
    x, y, _ = epoch(SceneBatches(inputs, targets, POSITIONS, batch_size=4, copies=3, seed=1))
    assert x.dtype == torch.float32
    rows = row_of(x)
    assert torch.equal(x, inputs[rows])  # unchanged: no normalisation
    assert torch.equal(y, targets[rows])
    assert torch.equal(y[:, 1], y[:, 0] * y[:, 0])


def test_drop_last_drops_the_short_batch():
    inputs, targets = feature_store()
    batches = SceneBatches(inputs, targets, POSITIONS, batch_size=7, copies=10, drop_last=True)
    assert len(batches) == 50 // 7 == 7
    x, _, sizes = epoch(batches)
    assert sizes == [7] * 7
    assert len(x) == 49
    # An exact multiple loses nothing.
    exact = SceneBatches(inputs, targets, POSITIONS, batch_size=5, copies=2, drop_last=True)
    assert len(exact) == 2 and epoch(exact)[2] == [5, 5]


def test_epochs_differ_and_a_seed_repeats_them():
    inputs, targets = feature_store()
    make = lambda seed: SceneBatches(inputs, targets, POSITIONS, 8, copies=4, seed=seed)  # noqa: E731
    a, b = make(5), make(5)
    first, second = row_of(epoch(a)[0]), row_of(epoch(a)[0])
    assert not torch.equal(first, second)  # a new order each epoch
    assert torch.equal(torch.sort(first).values, torch.sort(second).values)
    assert torch.equal(row_of(epoch(b)[0]), first)  # same seed, same epochs
    assert torch.equal(row_of(epoch(b)[0]), second)
    assert not torch.equal(row_of(epoch(make(6))[0]), first)


def test_no_shuffle_keeps_the_order():
    inputs, targets = feature_store()
    batches = SceneBatches(inputs, targets, POSITIONS, 3, shuffle=False, copies=2)
    x, _, sizes = epoch(batches)
    assert sizes == [3, 3, 3, 1]
    assert row_of(x).tolist() == [*POSITIONS.tolist(), *POSITIONS.tolist()]


def test_batch_size_must_be_positive():
    inputs, targets = feature_store()
    with pytest.raises(ValueError, match="batch_size=0"):
        SceneBatches(inputs, targets, POSITIONS, 0)


def test_uint8_images_come_out_normalised_float32():
    images = random_uint8(10, 8, 8, seed=9)
    targets = torch.arange(10, dtype=torch.float32)[:, None]  # target = the row
    batches = SceneBatches(images, targets, np.array([0, 2, 5, 6]), batch_size=3, copies=2)
    seen = []
    for x, y in batches:
        assert x.dtype == torch.float32 and x.shape[1:] == (3, 8, 8)
        rows = y[:, 0].long()
        assert torch.equal(x, normalize(images[rows]))
        seen += rows.tolist()
    assert sorted(seen) == [0, 0, 2, 2, 5, 5, 6, 6]


def test_augmented_images_are_flips_of_the_right_rows():
    images = random_uint8(10, 8, 8, seed=10)
    targets = torch.arange(10, dtype=torch.float32)[:, None]
    batches = SceneBatches(
        images,
        targets,
        np.arange(10),
        batch_size=5,
        copies=4,
        augment=Augment(flip_p=0.5, rotate_p=0.0),
        seed=2,
    )
    flipped = 0
    for x, y in batches:
        assert x.dtype == torch.float32
        rows = y[:, 0].long()
        plain = (x == normalize(images[rows])).flatten(1).all(1)
        mirrored = (x == normalize(F.horizontal_flip(images[rows]))).flatten(1).all(1)
        assert bool((plain | mirrored).all())
        flipped += int(mirrored.sum())
    assert 0 < flipped < 40


# --- noisy copies of the descriptors (the LEAP-HRI'24 benchmark's augmentation) -----------


def descriptor_store(n: int = 200) -> tuple[torch.Tensor, torch.Tensor]:
    """n scenes of 27 descriptors in 0..1 and 2 mode flags; target (scene, 0)."""
    gen = g(11)
    flags = torch.zeros(n, 2)
    flags[torch.arange(n) % 2 == 0, 0] = 1.0
    flags[:, 1] = 1 - flags[:, 0]
    inputs = torch.cat([torch.rand(n, 27, generator=gen), flags], 1)
    return inputs, torch.stack([torch.arange(n, dtype=torch.float32), torch.zeros(n)], 1)


def noisy_epoch(noise: InputNoise, copies: int, seed: int = 0, n: int = 200):
    inputs, targets = descriptor_store(n)
    batches = SceneBatches(
        inputs, targets, np.arange(n), 64, copies=copies, augment=noise, seed=seed
    )
    x, y, _ = epoch(batches)
    return inputs, x, y[:, 0].long(), batches


def test_descriptor_noise_gives_copies_rows_per_scene_with_the_noise_spread():
    """25 noisy copies of each of 200 training scenes, std 0.01 on the 27 descriptors: 5000
    training rows an epoch, each scene 25 times, no two copies alike; the noise's spread
    over 135,000 draws is 0.01 within 3% (its standard error is 0.2%); the mode flags
    untouched; the next epoch shows the same rows in another order."""
    inputs, x, scene, batches = noisy_epoch(InputNoise(0.01), copies=25)
    assert len(x) == batches.samples_per_epoch == 5000
    assert torch.bincount(scene, minlength=200).tolist() == [25] * 200
    noise = x - inputs[scene]
    assert torch.equal(noise[:, 27:], torch.zeros(5000, 2))
    assert float(noise[:, :27].std()) == pytest.approx(0.01, rel=0.03)
    assert abs(float(noise[:, :27].mean())) < 1e-4  # ~4 standard errors of the mean (2.7e-5)
    assert len(torch.unique(x, dim=0)) == 5000
    again, _, _ = epoch(batches)
    assert not torch.equal(again, x)
    assert torch.equal(torch.unique(again, dim=0), torch.unique(x, dim=0))


def test_descriptor_noise_is_seeded_and_leaves_the_order_as_without_it():
    _, x, scene, _ = noisy_epoch(InputNoise(0.01), copies=3, seed=4)
    _, same, _, _ = noisy_epoch(InputNoise(0.01), copies=3, seed=4)
    _, other, _, _ = noisy_epoch(InputNoise(0.01), copies=3, seed=5)
    assert torch.equal(x, same) and not torch.equal(x, other)
    _, plain, plain_scene, _ = noisy_epoch(None, copies=3, seed=4)
    assert not torch.equal(x, plain)
    assert torch.equal(scene, plain_scene)  # the noise draws nothing from the order's generator


def test_cumulative_noise_grows_as_the_square_root_of_the_copy():
    """The LEAP-HRI'24 code's copies, noised in place one after another: copy k's noise is
    the sum of k draws, std 0.01 x sqrt(k) (5,400 draws per copy: within 6%)."""
    draws = InputNoise(0.01, cumulative=True).draw(200, 25, 29, g(0)).view(25, 200, 29)
    for k in (1, 4, 9, 25):
        assert float(draws[k - 1, :, :27].std()) == pytest.approx(0.01 * math.sqrt(k), rel=0.06)
    steps = draws[1:] - draws[:-1]
    assert float(steps[:, :, :27].std()) == pytest.approx(0.01, rel=0.03)
    assert not draws[:, :, 27:].any()


def test_original_copy_is_the_scene_itself():
    """Its FL notebooks: the scene and 8 noisy copies, 9 rows per scene."""
    draws = InputNoise(0.01, original=True).draw(50, 9, 29, g(1)).view(9, 50, 29)
    assert not draws[0].any() and draws[1:, :, :27].all()


def test_augmenter_picks_the_modality_s_augmentation():
    from fedlgr.shell.config import DataConfig

    assert augmenter(DataConfig(augment=False), images=True) is None
    assert isinstance(augmenter(DataConfig(augment=True), images=True), Augment)
    data = DataConfig(modality="features", augment=True, noise={"std": 0.05, "original": True})
    noise = augmenter(data, images=False)
    assert isinstance(noise, InputNoise) and (noise.std, noise.original) == (0.05, True)
    assert noise.columns == 27 and not noise.cumulative


def test_descriptor_noise_settings_are_refused_where_they_would_do_nothing():
    from fedlgr.errors import ConfigError
    from fedlgr.shell.config import DataConfig

    with pytest.raises(ConfigError, match=r"^data.noise: the descriptors' noise, for data.mod"):
        DataConfig(modality="image", augment=True, noise={"std": 0.05})
    with pytest.raises(ConfigError, match=r"^data.noise.std=-0.1: must be >= 0$"):
        DataConfig(modality="features", noise={"std": -0.1})
