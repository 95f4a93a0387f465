"""Match scene images to stamps, decode them once into a uint8 tensor store, cached under a key
of the source files (name, size, mtime) and the settings: training never touches a PNG."""

from __future__ import annotations

import hashlib
import json
import os
import re
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torchvision.transforms.v2 import functional as F

from fedlgr.core.settings.rules import format_bytes
from fedlgr.errors import ConfigError, DataError, first_line, join_problems
from fedlgr.shell.checks.experiment import machine_memory
from fedlgr.shell.checks.paths import broken_link

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_STAMP_PREFIX = re.compile(r"^(\d+)(?!\d)")
CACHE_FORMAT = 1
# Smaller images are refused as degenerate (a 1x1 file among renders): they show no scene.
MIN_IMAGE_SIDE = 8

Crop = tuple[int | None, int | None, int | None, int | None]


@dataclass(frozen=True)
class ImageMatch:
    files: dict[int, Path]  # stamp -> image file
    missing: list[int]  # stamps without an image
    orphans: list[Path]  # image files whose name starts with no known stamp


def match_images(image_dir: Path, stamps: np.ndarray) -> ImageMatch:
    """Pair each stamp with the one image whose file name starts with it (``250.png``,
    ``250_scene.jpg``; ``2500.png`` is not stamp 250)."""
    if not image_dir.is_dir():
        raise DataError(
            f"{image_dir}: image folder not found (for the descriptor CSV alone "
            "use data.modality=features)"
        )
    known = set(stamps.tolist())
    files: dict[int, Path] = {}
    orphans, clashes = [], []
    for path in sorted(image_dir.iterdir()):
        if path.suffix.lower() not in IMAGE_SUFFIXES or not path.is_file():
            continue
        m = _STAMP_PREFIX.match(path.name)
        stamp = int(m.group(1)) if m else None
        if stamp not in known:
            orphans.append(path)
        elif stamp in files:
            clashes.append(f"stamp {stamp} matches both {files[stamp].name} and {path.name}")
        else:
            files[stamp] = path
    if clashes:
        raise DataError(join_problems(str(image_dir), clashes))
    missing = [s for s in stamps.tolist() if s not in files]
    return ImageMatch(files, missing, orphans)


def _listing(items: list, limit: int = 10) -> str:
    shown = ", ".join(map(str, items[:limit]))
    return shown + (f" and {len(items) - limit} more" if len(items) > limit else "")


def decode(path: Path, size: int, crop: Crop | None) -> torch.Tensor:
    """Read one image as RGB, crop it, resize it to ``size`` x ``size``: (3, S, S) uint8.
    Pillow decodes, as torchvision deprecated its own decoders for TorchCodec, a dependency more."""
    try:
        with Image.open(path) as file:
            width, height = file.size
            # Pillow only warns up to twice its decompression-bomb limit, and would decode
            if Image.MAX_IMAGE_PIXELS is not None and width * height > Image.MAX_IMAGE_PIXELS:
                raise DataError(_oversized(path, f"{width}x{height} = {width * height}"))
            if min(width, height) < MIN_IMAGE_SIDE:
                raise DataError(
                    f"{path}: {width}x{height} pixels, under the {MIN_IMAGE_SIDE} px a side that "
                    f"a scene needs (images of any size are resized to data.image_size={size}, "
                    "but one this small is degenerate)"
                )
            pixels = np.array(file.convert("RGB"))  # a writable copy for torch
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as err:
        # over twice the limit (or once, where warnings are errors): Pillow refuses to open
        pixels = re.search(r"\((\d+) pixels\)", str(err))
        raise DataError(_oversized(path, pixels.group(1) if pixels else "too many")) from err
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as err:
        raise DataError(f"{path}: cannot decode image ({first_line(err)})") from err
    image = torch.from_numpy(pixels).permute(2, 0, 1)
    if crop is not None:
        left, top, right, bottom = crop  # None: the image's edge
        if (right or 0) > width or (bottom or 0) > height:
            raise DataError(
                f"{path}: data.crop={list(crop)} reaches outside the {width}x{height} image"
            )
        image = image[:, top:bottom, left:right]
    return F.resize(image, [size, size], antialias=True).contiguous()


def _oversized(path: Path, pixels: str) -> str:
    return (
        f"{path}: image too large to decode safely ({pixels} pixels, over Pillow's "
        f"decompression-bomb limit PIL.Image.MAX_IMAGE_PIXELS={Image.MAX_IMAGE_PIXELS})"
    )


@dataclass(frozen=True)
class ImageStore:
    stamps: np.ndarray  # (N,) int64, the stamps that have an image
    images: torch.Tensor  # (N, 3, S, S) uint8
    skipped: tuple[str, ...] = ()  # files or stamps left out, with the reason


def _cache_key(files: list[Path], size: int, crop: Crop | None, policy: str) -> str:
    h = hashlib.sha256()
    h.update(json.dumps([CACHE_FORMAT, size, crop, policy]).encode())
    for path in files:
        st = path.stat()
        h.update(f"{path.resolve()}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:24]


def load_image_store(
    image_dir: Path,
    stamps: np.ndarray,
    size: int,
    crop: Crop | None = None,
    on_bad_image: str = "error",
    cache_dir: Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ImageStore:
    """Decode the image of every stamp once, or read the store from the cache; a scene without
    a usable image is dropped with a warning (``on_bad_image="skip"``) or refused (``"error"``)."""
    match = match_images(image_dir, stamps)
    if match.orphans:
        warnings.warn(
            f"{image_dir}: {len(match.orphans)} image(s) without a stamp in the CSV, "
            f"ignored: {_listing([p.name for p in match.orphans])}",
            stacklevel=2,
        )
    skipped = [f"stamp {s}: no image" for s in match.missing]
    if match.missing:
        listed = f"{len(match.missing)} stamp(s) of the CSV: {_listing(match.missing)}"
        if on_bad_image == "error":
            raise DataError(
                f"{image_dir}: no image for {listed} (data.on_bad_image=skip leaves them out)"
            )
        warnings.warn(f"{image_dir}: skipping, for want of an image, {listed}", stacklevel=2)

    wanted = [s for s in stamps.tolist() if s in match.files]
    files = [match.files[s] for s in wanted]
    _check_store_fits(len(files), size)
    cache_file = None
    if cache_dir is not None:
        _check_cache_dir(cache_dir)
        cache_file = cache_dir / f"images-{_cache_key(files, size, crop, on_bad_image)}.pt"
        if cache_file.is_file():
            cached = _read_cache(cache_file, wanted, size, len(match.missing))
            if cached is not None:
                return cached

    store = _decode_all(files, wanted, size, crop, on_bad_image, skipped, progress)
    if cache_file is not None:
        _save_atomically(store, cache_file)
    return store


def _check_store_fits(n: int, size: int) -> None:
    """Refuse a store larger than this machine's memory, before decoding or reading any."""
    store, have = n * 3 * size**2, machine_memory()
    if 2 * store > have:
        raise ConfigError(
            f"data.image_size={size}: the decoded images of {n} scenes take "
            f"{format_bytes(store)} ({n} x 3 x {size}^2 bytes) and twice that while they are "
            f"stacked, more than this machine's {format_bytes(have)} of memory "
            "(psutil.virtual_memory().total)"
        )


def _check_cache_dir(cache_dir: Path) -> None:
    """Refuse a cache folder that is, or lies under, a file, a device or a broken link, before
    decoding: after it, the cache could only be skipped with a warning, its decoding lost."""
    from_env = os.environ.get("FEDLGR_CACHE_DIR")
    setting = "FEDLGR_CACHE_DIR" if from_env and Path(from_env) == cache_dir else "data.cache_dir"
    if why := broken_link(cache_dir):
        raise ConfigError(
            f"{setting}={cache_dir}: {why} (point {setting} at a folder, or turn the cache "
            "off with data.cache=false)"
        )
    existing = next(p for p in (cache_dir, *cache_dir.parents) if p.exists())
    if not existing.is_dir():
        where = "" if existing == cache_dir else f": {existing}"
        what = "a file" if existing.is_file() else "a device, pipe or socket"
        raise ConfigError(
            f"{setting}={cache_dir}{where} is {what}; the image cache needs a folder "
            f"(point {setting} at one, or turn the cache off with data.cache=false)"
        )


def _read_cache(cache_file: Path, wanted: list[int], size: int, n_missing: int):
    """The store saved in ``cache_file`` if it is what its key promises, else ``None``
    (after a one-line warning: the caller decodes again and overwrites it)."""
    try:
        saved = torch.load(cache_file, weights_only=True)
    except Exception as err:
        # torch.load raises any of many errors on damage; a damaged cache is rebuilt, never fatal
        problem = f"unreadable image cache, decoding again ({first_line(err)})"
    else:
        if (mismatch := _cache_mismatch(saved, wanted, size, n_missing)) is None:
            return ImageStore(saved["stamps"].numpy(), saved["images"], tuple(saved["skipped"]))
        problem = f"image cache does not match its key ({mismatch}), decoding again"
    warnings.warn(f"{cache_file}: {problem}", stacklevel=3)
    return None


def _describe(value) -> str:
    if isinstance(value, torch.Tensor):
        return f"{tuple(value.shape)} {str(value.dtype).removeprefix('torch.')}"
    return type(value).__name__


def _cache_mismatch(saved, wanted: list[int], size: int, n_missing: int) -> str | None:
    """Why ``saved`` is not the store its key promises, or ``None``: uint8 ``(N, 3, size, size)``
    images of stamps in ``wanted``'s order, and ``N + len(skipped) == len(wanted) + n_missing``."""
    if not isinstance(saved, dict) or not {"stamps", "images", "skipped"} <= saved.keys():
        return "not a dict of stamps, images and skipped"
    stamps, images, skipped = saved["stamps"], saved["images"], saved["skipped"]
    if not (isinstance(stamps, torch.Tensor) and stamps.dtype == torch.int64 and stamps.ndim == 1):
        return f"stamps {_describe(stamps)}, expected (N,) int64"
    expected = f"{(len(stamps), 3, size, size)} uint8"
    if _describe(images) != expected:
        return f"images {_describe(images)}, expected {expected}"
    position = {s: k for k, s in enumerate(wanted)}
    order = [position.get(s, -1) for s in stamps.tolist()]
    if not order or -1 in order or order != sorted(set(order)):
        return "its stamps are not those of the image files"
    n_skipped = len(skipped) if isinstance(skipped, list | tuple) else "?"
    if n_skipped == "?" or len(stamps) + n_skipped != len(wanted) + n_missing:
        return (
            f"{len(stamps)} images and {n_skipped} skipped, "
            f"expected {len(wanted) + n_missing} scenes in all"
        )
    return None


def _decode_all(files, stamps, size, crop, on_bad_image, skipped, progress) -> ImageStore:
    def one(path):
        try:
            return decode(path, size, crop)
        except DataError as err:
            return err

    images, kept = [], []
    # Pillow's decoders and torch's resize release the GIL: threads scale here.
    with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
        for k, (stamp, result) in enumerate(zip(stamps, pool.map(one, files), strict=True)):
            if isinstance(result, DataError):
                if on_bad_image == "error":
                    raise result
                skipped.append(str(result))
                warnings.warn(f"skipping stamp {stamp}: {result}", stacklevel=3)
            else:
                images.append(result)
                kept.append(stamp)
            if progress is not None:
                progress(k + 1, len(files))
    if not images:
        raise DataError("no usable images: every scene was skipped")
    return ImageStore(np.asarray(kept, dtype=np.int64), torch.stack(images), tuple(skipped))


def _save_atomically(store: ImageStore, cache_file: Path) -> None:
    tmp = cache_file.with_suffix(f".tmp{os.getpid()}")
    payload = {
        "stamps": torch.from_numpy(store.stamps),
        "images": store.images,
        "skipped": list(store.skipped),
    }
    try:
        cache_file.parent.mkdir(parents=True, exist_ok=True)
        torch.save(payload, tmp)
        tmp.replace(cache_file)
    except (OSError, RuntimeError) as err:  # a read-only or full cache folder: the run goes on
        # (torch.save reports a failed write as a RuntimeError: "unexpected pos ...")
        tmp.unlink(missing_ok=True)
        reason = first_line(err, 200)
        warnings.warn(f"{cache_file}: could not write the image cache ({reason})", stacklevel=3)
