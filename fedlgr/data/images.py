"""Match scene images to stamps, decode them once into a uint8 tensor store, cache it.

Images are decoded, cropped and resized exactly once (``decode`` below); the resulting
``(N, 3, S, S)`` uint8 tensor is kept in memory and saved under the cache folder keyed by
the source files (name, size, modification time) and the settings, so a second load of
the same data reads one file and decodes nothing. Training never touches a PNG.
"""

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

from fedlgr.errors import DataError, join_problems

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_STAMP_PREFIX = re.compile(r"^(\d+)(?!\d)")
CACHE_FORMAT = 1

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

    Pillow decodes (torchvision 0.29 deprecated its own decoders in favour of TorchCodec,
    a further dependency); resizing is torchvision's v2 antialiased resize on the tensor.
    """
    try:
        with Image.open(path) as file:
            pixels = np.array(file.convert("RGB"))  # a writable copy for torch
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as err:
        raise DataError(f"{path}: cannot decode image ({str(err).splitlines()[0]})") from err
    image = torch.from_numpy(pixels).permute(2, 0, 1)
    if crop is not None:
        height, width = image.shape[-2:]
        left, top, right, bottom = crop
        left, top = left or 0, top or 0
        right = width if right is None else right
        bottom = height if bottom is None else bottom
        if right > width or bottom > height:
            raise DataError(
                f"{path}: data.crop={list(crop)} reaches outside the {width}x{height} image"
            )
        image = image[:, top:bottom, left:right]
    return F.resize(image, [size, size], antialias=True).contiguous()


@dataclass(frozen=True)
class ImageStore:
    stamps: np.ndarray  # (N,) int64, the stamps that have an image
    images: torch.Tensor  # (N, 3, S, S) uint8
    skipped: tuple[str, ...] = ()  # files or stamps left out, with the reason
    from_cache: bool = False


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
    """Decode the image of every stamp once, or read the store from the cache.

    ``on_bad_image="skip"`` drops scenes whose image is missing or cannot be decoded, with a
    warning naming them; ``"error"`` raises a :class:`DataError` naming the file/stamps.
    """
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
    cache_file = None
    if cache_dir is not None:
        cache_file = cache_dir / f"images-{_cache_key(files, size, crop, on_bad_image)}.pt"
        if cache_file.is_file():
            try:
                saved = torch.load(cache_file, weights_only=True)
                return ImageStore(
                    saved["stamps"].numpy(),
                    saved["images"],
                    tuple(saved["skipped"]),
                    from_cache=True,
                )
            except Exception as err:
                # raises IndexError, UnpicklingError, ... on damage) is rebuilt, never fatal
                warnings.warn(
                    f"{cache_file}: unreadable image cache, decoding again ({err})", stacklevel=2
                )

    store = _decode_all(files, wanted, size, crop, on_bad_image, skipped, progress)
    if cache_file is not None:
        _save_atomically(store, cache_file)
    return store


def _decode_all(files, stamps, size, crop, on_bad_image, skipped, progress) -> ImageStore:
    if on_bad_image == "skip":

        def one(path):
            try:
                return decode(path, size, crop)
            except DataError as err:
                return err
    else:
        one = lambda path: decode(path, size, crop)  # noqa: E731
    images, kept = [], []
    # Pillow's decoders and torch's resize release the GIL: threads scale here.
    with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
        for k, (stamp, result) in enumerate(zip(stamps, pool.map(one, files), strict=True)):
            if isinstance(result, DataError):
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
    cache_file.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache_file.with_suffix(f".tmp{os.getpid()}")
    payload = {
        "stamps": torch.from_numpy(store.stamps),
        "images": store.images,
        "skipped": list(store.skipped),
    }
    try:
        torch.save(payload, tmp)
        tmp.replace(cache_file)
    except OSError as err:  # a read-only cache folder must not stop the run
        tmp.unlink(missing_ok=True)
        warnings.warn(f"{cache_file}: could not write the image cache ({err})", stacklevel=3)
