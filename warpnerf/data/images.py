"""Image reading shared by the loaders: decode, check size, area-downscale, in a thread pool; and
:func:`image_header`, an image's size and channels without decoding it (cameras-only loads)."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence

import numpy as np

from warpnerf.data.errors import DatasetError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".bmp", ".tif", ".tiff")


def read_image(path: str) -> np.ndarray:
    """Decode an image to float32 in [0, 1], shape (H, W, C) with C in {1, 3, 4}.

    Raises DatasetError naming the file when it is missing or cannot be decoded.
    """
    if not os.path.isfile(path):
        raise DatasetError(f"missing image {path}")
    try:
        if path.lower().endswith((".png", ".jpg", ".jpeg")):
            # Pillow directly: imageio's plugin dispatch costs ~30 % on small PNGs.
            from PIL import Image  # lazy: codecs stay out of --help (~0.08 s)

            with Image.open(path) as im:
                if im.mode not in ("L", "LA", "RGB", "RGBA", "I;16"):
                    im = im.convert("RGBA")  # palette, 1-bit, CMYK...: asarray would return raw codes
                img = np.asarray(im)
        else:
            import imageio.v3 as iio  # lazy: codecs stay out of --help (~0.08 s)

            img = iio.imread(path)
    except Exception as exc:  # decoders raise many types; the user needs the file name, not the type
        raise DatasetError(f"cannot read image {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[-1] not in (1, 2, 3, 4):
        raise DatasetError(f"unsupported image shape {img.shape} in {path}")
    if img.shape[-1] == 2:  # grey + alpha
        img = np.concatenate([img[..., :1].repeat(3, -1), img[..., 1:]], -1)
    if img.dtype == np.uint8:
        return img.astype(np.float32) * (1.0 / 255.0)
    if img.dtype == np.uint16:
        return img.astype(np.float32) * (1.0 / 65535.0)
    return img.astype(np.float32)


# PIL modes read_image keeps as they are, and the channels it returns for them; any other mode is
# converted to RGBA (4 channels)
_MODE_CHANNELS = {"L": 1, "LA": 4, "RGB": 3, "RGBA": 4, "I;16": 1}


def image_header(path: str) -> tuple[int, int, int]:
    """(height, width, channels) that :func:`read_image` would return the shape of, read from the file's
    header without decoding its pixels (PIL opens lazily) for PNG and JPEG; other formats (EXR, BMP,
    TIFF) are decoded. Raises DatasetError as :func:`read_image` does for a missing or unreadable file."""
    if not os.path.isfile(path):
        raise DatasetError(f"missing image {path}")
    if not path.lower().endswith((".png", ".jpg", ".jpeg")):
        h, w, c = read_image(path).shape
        return h, w, c
    try:
        from PIL import Image  # lazy: codecs stay out of --help (~0.08 s)

        with Image.open(path) as im:
            (w, h), mode = im.size, im.mode
    except Exception as exc:  # as read_image: the user needs the file name, not the type
        raise DatasetError(f"cannot read image {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    return int(h), int(w), _MODE_CHANNELS.get(mode, 4)


def image_headers(paths: list[str]) -> list[tuple[int, int, int]]:
    """:func:`image_header` of every path, in a thread pool (:func:`load_parallel`), in order."""
    heads: list = [None] * len(paths)

    def head(i: int, path: str) -> None:
        heads[i] = image_header(path)

    load_parallel(paths, head)
    return heads


def area_downscale(img: np.ndarray, factor: int) -> np.ndarray:
    """Average ``factor`` x ``factor`` blocks of (H, W, ...) -> (H // factor, W // factor, ...).

    Rows/columns beyond a multiple of ``factor`` (bottom/right) are dropped. The principal
    point stays at cx / factor because block k covers source pixels [k f, (k + 1) f).
    """
    if factor == 1:
        return img
    h, w = img.shape[0] // factor, img.shape[1] // factor
    if h == 0 or w == 0:
        raise DatasetError(f"downscale factor {factor} is larger than the image ({img.shape[1]}x{img.shape[0]})")
    blocks = img[: h * factor, : w * factor].reshape(h, factor, w, factor, *img.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float32)


def downscaled_size(height: int, width: int, factor: int) -> tuple[int, int]:
    """(height, width) of an image after :func:`area_downscale` by ``factor``, with its DatasetError when
    the factor is larger than the image (cameras-only loads, which downscale no pixels)."""
    h, w = height // factor, width // factor
    if h == 0 or w == 0:
        raise DatasetError(f"downscale factor {factor} is larger than the image ({width}x{height})")
    return h, w


def downscale_depth(depth: np.ndarray, factor: int) -> np.ndarray:
    """Block average of a (H, W) depth map over its non-background (> 0) pixels; 0 where none."""
    if factor == 1:
        return depth
    h, w = depth.shape[0] // factor, depth.shape[1] // factor
    blocks = depth[: h * factor, : w * factor].reshape(h, factor, w, factor)
    hits = (blocks > 0).sum(axis=(1, 3))
    total = blocks.sum(axis=(1, 3))
    return np.where(hits > 0, total / np.maximum(hits, 1), 0.0).astype(np.float32)


def load_parallel(paths: Sequence[str], fn: Callable[[int, str], None], threads: int | None = None) -> None:
    """Call ``fn(i, path)`` for every path on a small thread pool (PNG decoding releases the GIL).

    The first DatasetError raised by any call is re-raised here.
    """
    threads = threads or min(4, os.cpu_count() or 2)  # measured: 8 threads on 2 cores is slower than 2
    if threads <= 1 or len(paths) <= 1:
        for i, p in enumerate(paths):
            fn(i, p)
        return
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="warpnerf-io") as pool:
        for fut in [pool.submit(fn, i, p) for i, p in enumerate(paths)]:
            fut.result()
