"""Images: matching stamps to files, bad files, crop and resize, and decode-once caching."""

from __future__ import annotations

import dataclasses
import os
import warnings

import numpy as np
import pytest
import torch
from PIL import Image

import fedlgr.shell.data.images as images_module
from fedlgr.errors import ConfigError, DataError
from fedlgr.shell.cli import main
from fedlgr.shell.config import DataConfig
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.images import decode, load_image_store, match_images
from tests.support.data import rating_row, write_dataset


def _png(path, colour=(200, 10, 10), size=(40, 30)):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, colour).save(path)
    return path


def test_images_match_stamps_by_prefix(tmp_path):
    d = tmp_path / "images"
    _png(d / "250.png")
    _png(d / "251_scene.jpg")
    _png(d / "2520.png")  # starts with 252, not with a known stamp
    _png(d / "scene_253.png")  # does not start with a stamp
    (d / "notes.txt").write_text("not an image")
    match = match_images(d, np.array([250, 251, 252, 254]))
    assert {s: p.name for s, p in match.files.items()} == {250: "250.png", 251: "251_scene.jpg"}
    assert match.missing == [252, 254]
    assert [p.name for p in match.orphans] == ["2520.png", "scene_253.png"]


def test_two_images_for_one_stamp_is_an_error(tmp_path):
    _png(tmp_path / "images" / "250.png")
    _png(tmp_path / "images" / "250_b.png")
    with pytest.raises(DataError, match=r"images: stamp 250 matches both 250.png and 250_b.png"):
        match_images(tmp_path / "images", np.array([250]))


def test_missing_images_error_names_the_stamps(synth_copy, cache_dir):
    (synth_copy / "images" / "251.png").unlink()
    (synth_copy / "images" / "260.png").unlink()
    with pytest.raises(DataError) as err:
        load_scenes(DataConfig(path=synth_copy, image_size=16, cache_dir=cache_dir))
    message = str(err.value)
    assert str(synth_copy / "images") in message
    assert "no image for 2 stamp(s) of the CSV: 251, 260" in message
    assert "data.on_bad_image=skip" in message


def test_missing_images_can_be_skipped_with_a_warning(synth_copy, cache_dir):
    (synth_copy / "images" / "251.png").unlink()
    with pytest.warns(UserWarning, match="skipping, for want of an image, 1 stamp.*: 251"):
        scenes = load_scenes(
            DataConfig(path=synth_copy, image_size=16, cache_dir=cache_dir, on_bad_image="skip")
        )
    assert len(scenes) == 47 and 251 not in scenes.stamps.tolist()
    assert len(scenes.images) == len(scenes.targets) == 47


def test_images_without_a_stamp_are_reported(synth_copy, cache_dir):
    _png(synth_copy / "images" / "999.png")
    with pytest.warns(
        UserWarning, match=r"1 image\(s\) without a stamp in the CSV, ignored: 999.png"
    ):
        scenes = load_scenes(DataConfig(path=synth_copy, image_size=16, cache_dir=cache_dir))
    assert len(scenes) == 48


def test_corrupt_image_names_the_file(synth_copy, cache_dir):
    bad = synth_copy / "images" / "255.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n this is not really a png")
    with pytest.raises(DataError, match="cannot decode image") as err:
        load_scenes(DataConfig(path=synth_copy, image_size=16, cache_dir=cache_dir))
    assert str(err.value).startswith(f"{bad}: ")


def test_corrupt_image_can_be_skipped(synth_copy, cache_dir):
    (synth_copy / "images" / "255.png").write_bytes(b"garbage")
    with pytest.warns(UserWarning, match=r"skipping stamp 255: .*255.png: cannot decode image"):
        scenes = load_scenes(
            DataConfig(path=synth_copy, image_size=16, cache_dir=cache_dir, on_bad_image="skip")
        )
    assert 255 not in scenes.stamps.tolist() and len(scenes.images) == 47


def test_cli_reports_a_corrupt_image_in_one_line(synth_copy, cache_dir, capsys):
    bad = synth_copy / "images" / "255.png"
    bad.write_bytes(b"garbage")
    assert main(["data", "check", str(synth_copy), "--size", "16"]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith(f"fedlgr: error: {bad}: cannot decode image") and err.count("\n") == 1


def test_crop_then_resize(tmp_path):
    # Left 10 columns red, right 30 blue: cropping x in [10, 40) leaves only blue.
    image = Image.new("RGB", (40, 20), (0, 0, 255))
    image.paste((255, 0, 0), (0, 0, 10, 20))
    path = tmp_path / "1.png"
    image.save(path)
    full = decode(path, 8, None)
    assert full.shape == (3, 8, 8) and full.dtype == torch.uint8
    assert full[0, :, 0].min() > 200  # red at the left edge
    cropped = decode(path, 8, (10, None, None, None))
    assert cropped[0].max() == 0 and cropped[2].min() == 255
    top = decode(path, 4, (None, 0, 10, 5))
    assert top[0].min() == 255 and top[2].max() == 0


def test_crop_outside_the_image_names_file_and_setting(tmp_path):
    path = _png(tmp_path / "1.png", size=(40, 20))
    with pytest.raises(
        DataError,
        match=r"1.png: data.crop=\[295, None, 1313, None\] reaches "
        r"outside the 40x20 image",
    ):
        decode(path, 8, (295, None, 1313, None))


def test_crop_setting_is_validated():
    with pytest.raises(
        ConfigError, match=r"data.crop=\[10, 0, 5, 20\]: right \(5\) must exceed left"
    ):
        DataConfig(crop=(10, 0, 5, 20))
    with pytest.raises(ConfigError, match=r"data\.crop=\[1, 2, 3\]: must be \[left, top, right"):
        DataConfig(crop=(1, 2, 3))


def test_jpeg_images_decode(tmp_path):
    path = tmp_path / "7_render.jpg"
    Image.new("RGB", (32, 32), (0, 200, 0)).save(path, quality=95)
    image = decode(path, 16, None)
    assert image[1].float().mean() > 190 and image[0].float().mean() < 15


def _count_decodes(monkeypatch):
    calls = []
    real = images_module.decode

    def counting(path, size, crop):
        calls.append(path)
        return real(path, size, crop)

    monkeypatch.setattr(images_module, "decode", counting)
    return calls


def test_second_load_decodes_nothing(synth_dir, cache_dir, monkeypatch):
    calls = _count_decodes(monkeypatch)
    config = DataConfig(path=synth_dir, image_size=24, cache_dir=cache_dir)
    first = load_scenes(config)
    assert len(calls) == 48
    second = load_scenes(config)
    assert len(calls) == 48  # not one more decode
    assert torch.equal(first.images, second.images)
    np.testing.assert_array_equal(first.stamps, second.stamps)
    assert len(list(cache_dir.glob("images-*.pt"))) == 1


def test_cache_follows_files_and_settings(synth_copy, cache_dir, monkeypatch):
    calls = _count_decodes(monkeypatch)
    config = DataConfig(path=synth_copy, image_size=24, cache_dir=cache_dir)
    load_scenes(config)
    load_scenes(DataConfig(path=synth_copy, image_size=16, cache_dir=cache_dir))
    assert len(calls) == 96  # another size is another store
    changed = synth_copy / "images" / "260.png"
    _png(changed, colour=(1, 2, 3), size=(32, 32))
    os.utime(changed, ns=(1, 1))
    scenes = load_scenes(config)
    assert len(calls) == 144  # a changed source file invalidates the store
    assert scenes.images[scenes.stamps.tolist().index(260)].float().mean() < 4


def test_unreadable_cache_is_rebuilt(synth_dir, cache_dir, monkeypatch):
    config = DataConfig(path=synth_dir, image_size=20, cache_dir=cache_dir)
    load_scenes(config)
    (cache_file,) = cache_dir.glob("images-*.pt")
    cache_file.write_bytes(b"truncated")
    calls = _count_decodes(monkeypatch)
    with pytest.warns(UserWarning, match="unreadable image cache, decoding again"):
        scenes = load_scenes(config)
    assert len(calls) == 48 and scenes.images.shape == (48, 3, 20, 20)


def test_cache_can_be_turned_off(synth_dir, cache_dir, monkeypatch):
    calls = _count_decodes(monkeypatch)
    config = DataConfig(path=synth_dir, image_size=20, cache_dir=cache_dir, cache=False)
    load_scenes(config)
    load_scenes(config)
    assert len(calls) == 96 and not cache_dir.exists()


def test_store_order_follows_the_stamps(synth_dir, cache_dir):
    with pytest.warns(UserWarning, match="45 image"):  # the other 45 scenes' files
        store = load_image_store(synth_dir / "images", np.array([260, 250, 255]), 16)
    assert store.stamps.tolist() == [260, 250, 255]
    assert torch.equal(store.images[1], decode(synth_dir / "images" / "250.png", 16, None))


def _wrong_shape(saved):
    return {**saved, "images": saved["images"][:, :, :16, :16].contiguous()}


def _wrong_dtype(saved):
    return {**saved, "images": saved["images"].float()}


def _one_image_short(saved):
    return {**saved, "stamps": saved["stamps"][1:], "images": saved["images"][1:]}


def _other_stamps(saved):
    return {**saved, "stamps": saved["stamps"] + 1000}


@pytest.mark.parametrize(
    ("damage", "problem"),
    [
        (_wrong_shape, "images (48, 3, 16, 16) uint8, expected (48, 3, 20, 20) uint8"),
        (_wrong_dtype, "images (48, 3, 20, 20) float32, expected (48, 3, 20, 20) uint8"),
        (_one_image_short, "47 images and 0 skipped, expected 48 scenes in all"),
        (_other_stamps, "its stamps are not those of the image files"),
        (lambda saved: saved["images"], "not a dict of stamps, images and skipped"),
    ],
)
def test_readable_cache_that_does_not_match_its_key_is_rebuilt(
    synth_dir, cache_dir, monkeypatch, damage, problem
):
    config = DataConfig(path=synth_dir, image_size=20, cache_dir=cache_dir)
    fresh = load_scenes(config)
    (cache_file,) = cache_dir.glob("images-*.pt")
    torch.save(damage(torch.load(cache_file, weights_only=True)), cache_file)
    calls = _count_decodes(monkeypatch)
    with pytest.warns(UserWarning) as caught:
        scenes = load_scenes(config)
    assert [str(w.message) for w in caught] == [
        f"{cache_file}: image cache does not match its key ({problem}), decoding again"
    ]
    assert len(calls) == 48
    assert torch.equal(scenes.images, fresh.images)
    np.testing.assert_array_equal(scenes.stamps, fresh.stamps)
    again = load_scenes(config)  # the rebuilt cache is used as is
    assert len(calls) == 48 and torch.equal(again.images, fresh.images)


def test_cache_with_skipped_images_is_accepted(synth_copy, cache_dir, monkeypatch):
    (synth_copy / "images" / "255.png").write_bytes(b"garbage")
    (synth_copy / "images" / "260.png").unlink()
    config = DataConfig(path=synth_copy, image_size=16, cache_dir=cache_dir, on_bad_image="skip")
    with pytest.warns(UserWarning):
        load_scenes(config)
    calls = _count_decodes(monkeypatch)
    with pytest.warns(UserWarning, match="skipping, for want of an image, 1 stamp"):
        scenes = load_scenes(config)
    assert calls == [] and len(scenes.images) == 46


def test_cache_dir_that_is_a_file_names_the_setting(synth_dir, tmp_path, capsys, monkeypatch):
    file = tmp_path / "cache-file"
    file.write_text("not a folder")
    with pytest.raises(ConfigError) as err:
        load_scenes(DataConfig(path=synth_dir, image_size=16, cache_dir=file))
    assert str(err.value) == (
        f"data.cache_dir={file} is a file; the image cache needs a folder "
        "(point data.cache_dir at one, or turn the cache off with data.cache=false)"
    )
    with pytest.raises(ConfigError, match=rf"data.cache_dir={file / 'sub'}: {file} is a file"):
        load_scenes(DataConfig(path=synth_dir, image_size=16, cache_dir=file / "sub"))
    monkeypatch.setenv("FEDLGR_CACHE_DIR", str(file))
    assert main(["data", "check", str(synth_dir), "--size", "16"]) == 1
    assert capsys.readouterr().err == (
        f"fedlgr: error: FEDLGR_CACHE_DIR={file} is a file; the image cache needs a folder "
        "(point FEDLGR_CACHE_DIR at one, or turn the cache off with data.cache=false)\n"
    )
    # the features modality reads no cache, so a misplaced one does not stop it
    assert len(load_scenes(DataConfig(path=synth_dir, modality="features"))) == 48


# A 64x64 PNG among 32x32 ones, with Pillow's decompression-bomb limit lowered in between:
# at 1500 pixels Pillow refuses it (4096 > 2 * 1500), at 2500 it only warns (and would decode).
BOMB_LIMITS = {1500: "4096", 2500: "64x64 = 4096"}


def _oversized_image(folder, monkeypatch, limit):
    bad = _png(folder / "images" / "255.png", size=(64, 64))
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", limit)
    reason = (
        f"{bad}: image too large to decode safely ({BOMB_LIMITS[limit]} pixels, over Pillow's "
        f"decompression-bomb limit PIL.Image.MAX_IMAGE_PIXELS={limit})"
    )
    return bad, reason


def _messages(caught, category=UserWarning):
    return [str(w.message) for w in caught if w.category is category]


@pytest.mark.parametrize("limit", BOMB_LIMITS)
def test_oversized_image_is_a_bad_image(synth_copy, cache_dir, monkeypatch, capsys, limit):
    _, reason = _oversized_image(synth_copy, monkeypatch, limit)
    config = DataConfig(path=synth_copy, image_size=16, cache_dir=cache_dir)
    with pytest.raises(DataError) as err, warnings.catch_warnings(record=True):
        load_scenes(config)
    assert str(err.value) == reason
    with warnings.catch_warnings(record=True):
        assert main(["data", "check", str(synth_copy), "--size", "16"]) == 1
    assert capsys.readouterr().err.splitlines()[-1] == f"fedlgr: error: {reason}"

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scenes = load_scenes(dataclasses.replace(config, on_bad_image="skip"))
    assert _messages(caught) == [f"skipping stamp 255: {reason}"]
    assert 255 not in scenes.stamps.tolist() and scenes.images.shape == (47, 3, 16, 16)


def test_oversized_image_is_refused_where_warnings_are_errors(synth_copy, monkeypatch):
    bad, _ = _oversized_image(synth_copy, monkeypatch, 2500)
    with warnings.catch_warnings():
        warnings.simplefilter("error", Image.DecompressionBombWarning)
        with pytest.raises(DataError, match=r"255.png: image too large to decode safely \(4096 "):
            decode(bad, 16, None)


def test_a_degenerate_image_is_refused_and_can_be_skipped(tmp_path, cache_dir):
    """A bad input of issue 20 (points 8 and 9)."""
    rows = [rating_row(s, True, [3] * 8) for s in (250, 251, 252)]
    folder = write_dataset(tmp_path / "data", rows, {250: (32, 32), 251: (1, 1), 252: (32, 7)})
    with pytest.raises(DataError) as caught:
        load_scenes(DataConfig(path=folder, image_size=16, cache=False))
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"{folder / 'images' / '251.png'}: 1x1 pixels, under the 8 px")
    assert "resized to data.image_size=16" in message
    config = DataConfig(path=folder, image_size=16, cache=False, on_bad_image="skip")
    with pytest.warns(UserWarning) as warned:
        scenes = load_scenes(config)
    assert scenes.stamps.tolist() == [250]
    skipped = sorted(str(w.message).split(": ", 1)[0] for w in warned)
    assert skipped == ["skipping stamp 251", "skipping stamp 252"]
    assert "252.png: 32x7 pixels" in str(warned[-1].message) + str(warned[0].message)


def test_an_image_store_larger_than_the_memory_is_refused_before_decoding(tmp_path, monkeypatch):
    """A bad input of issue 20 (points 8 and 9)."""
    rows = [rating_row(s, True, [3] * 8) for s in (250, 251)]
    folder = write_dataset(tmp_path / "data", rows, {250: (32, 32), 251: (32, 32)})
    monkeypatch.setattr(images_module, "machine_memory", lambda: 700_000, raising=False)

    def never(*args):
        raise AssertionError("decoded although the store cannot fit")

    monkeypatch.setattr(images_module, "decode", never)
    with pytest.raises(ConfigError) as caught:
        load_scenes(DataConfig(path=folder, image_size=256, cache=False))
    assert str(caught.value) == (
        "data.image_size=256: the decoded images of 2 scenes take 393.2 kB (2 x 3 x 256^2 "
        "bytes) and twice that while they are stacked, more than this machine's 700.0 kB of "
        "memory (psutil.virtual_memory().total)"
    )
