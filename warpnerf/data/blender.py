"""Loader for the Blender (NeRF-synthetic) layout.

A scene folder holds ``transforms_{train,val,test}.json`` and the images they name::

    {"camera_angle_x": 0.691,                 # horizontal field of view, radians
     "depth_scale": 5000.0,                   # optional: 16-bit depth PNG value per scene unit
     "frames": [{"file_path": "./train/r_0",  # ".png" appended when the path has no image suffix
                 "transform_matrix": [[...4 floats...] x 4],   # camera-to-world, OpenGL
                 "depth_path": "./train/r_0_depth.png"},       # optional (built-in scenes write it)
                ...]}

Images are RGBA composited on the background (``rgb * a + bg * (1 - a)``). Depth files are
16-bit PNGs (value / depth_scale = camera-z distance, 0 = background) or float ``.npy`` arrays
in scene units. ``fl_x`` (+ optional ``cx``, ``cy``) may replace ``camera_angle_x``
(instant-ngp style); pixels are assumed square.
"""

from __future__ import annotations

import math
import os
import sys

import numpy as np
import torch

from warpnerf.data.errors import DatasetError, check_frames, check_intrinsics, json_number, read_json_object
from warpnerf.data.images import (IMAGE_SUFFIXES, area_downscale, downscale_depth, downscaled_size, image_headers,
                                  load_parallel, read_image)
from warpnerf.data.scene import Scene, Views, stand_in
from warpnerf.geometry.rayspace import RaySpace

BLENDER_NEAR, BLENDER_FAR = 2.0, 6.0
BLENDER_AABB = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)


def load_blender(
    root: str,
    downscale: int = 1,
    splits: tuple[str, ...] = ("train", "val", "test"),
    white_background: bool = True,
    keep_alpha: bool = True,
    name: str | None = None,
    allow_rgb: bool = False,
    pixels: bool = True,
) -> Scene:
    """Load a Blender-layout scene folder into a :class:`Scene` (source "dataset", kind "blender").

    Args:
        root: folder holding ``transforms_*.json``.
        downscale: integer factor; images (and depth) are block-averaged, focal divided.
        splits: which splits to read; must include "train" and "test". A missing
            ``transforms_val.json`` just leaves ``scene.val`` None.
        white_background: composite on white (the standard protocol) rather than black.
        keep_alpha: also return the (N, H, W) alpha in ``Views.alpha``.
        name: scene name (default: the folder name).
        allow_rgb: accept images without alpha (one warning line). Off by default: the layout
            promises RGBA, and RGB renders on black scored against a white background are garbage.
        pixels: False: a cameras-only load (:mod:`warpnerf.data.scene`): every image's size and channels
            come from its header, no pixel is decoded, the images, alpha and depth are stand-ins; the checks
            of sizes, channels and depth files (existence, size) are those of the full load.

    Raises:
        DatasetError: missing folder or file, malformed JSON or missing key, unreadable
            image, images of different sizes within a split. The message names the culprit.
    """
    if "train" not in splits or "test" not in splits:
        raise ValueError(f"splits must include 'train' and 'test', got {splits}")
    if not isinstance(downscale, int) or downscale < 1:
        raise DatasetError(f"downscale must be a positive integer, got {downscale!r}")
    if not os.path.isdir(root):
        raise DatasetError(f"scene folder not found: {root}")
    bg = (1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0)
    views = {}
    for split in splits:
        path = os.path.join(root, f"transforms_{split}.json")
        if split == "val" and not os.path.isfile(path):
            continue
        views[split] = _load_split(root, path, downscale, bg, keep_alpha, allow_rgb, pixels)
    return Scene(
        name=name or os.path.basename(os.path.normpath(root)),
        source="dataset",
        kind="blender",
        train=views["train"],
        test=views["test"],
        val=views.get("val"),
        ray_space=RaySpace.euclidean(BLENDER_AABB, BLENDER_NEAR, BLENDER_FAR),
        background=bg,
        root=os.path.abspath(root),
        pixels=pixels,
    )


def read_transforms(path: str) -> dict:
    """Parse and validate one ``transforms_*.json``; raises DatasetError naming the file and key."""
    meta = read_json_object(path, " (a Blender scene needs transforms_train.json and transforms_test.json)")
    if "camera_angle_x" not in meta and "fl_x" not in meta:
        raise DatasetError(f"{path}: missing key 'camera_angle_x'")
    check_frames(path, meta.get("frames"))
    return meta


def _image_path(root: str, file_path: str) -> str:
    p = os.path.normpath(os.path.join(root, file_path))
    if os.path.splitext(p)[1].lower() in IMAGE_SUFFIXES:
        return p
    return p + ".png"


def read_depth(path: str, depth_scale: float | None) -> np.ndarray:
    """(H, W) float32 camera-z depth from a 16-bit PNG (/ depth_scale) or a float .npy."""
    if not os.path.isfile(path):
        raise DatasetError(f"missing depth file {path}")
    try:
        if path.endswith(".npy"):
            return np.load(path).astype(np.float32)
        import imageio.v3 as iio  # lazy: codecs stay out of --help (~0.08 s)

        raw = iio.imread(path)
    except Exception as exc:
        raise DatasetError(f"cannot read depth file {path}: {exc}") from None
    if depth_scale is None:
        raise DatasetError(f"depth file {path} is a PNG but the transforms file has no 'depth_scale'")
    return raw.astype(np.float32) / float(depth_scale)


def depth_header(path: str) -> tuple[int, int]:
    """(height, width) of a depth file (16-bit PNG or .npy) without reading its values; DatasetError as
    :func:`read_depth` for a missing or unreadable file."""
    if not os.path.isfile(path):
        raise DatasetError(f"missing depth file {path}")
    try:
        if path.endswith(".npy"):
            shape = np.load(path, mmap_mode="r").shape
        else:
            from PIL import Image  # lazy: codecs stay out of --help (~0.08 s)

            with Image.open(path) as im:
                shape = im.size[::-1]
    except Exception as exc:
        raise DatasetError(f"cannot read depth file {path}: {exc}") from None
    return int(shape[0]), int(shape[1] if len(shape) > 1 else 0)


def _check_channels(first_path: str, channels: int, allow_rgb: bool) -> None:
    """The Blender layout promises RGBA: an RGB first image is refused, or (``allow_rgb``) used with a warning."""
    if channels != 4:
        if not allow_rgb:
            raise DatasetError(f"{first_path} has no alpha channel but the Blender layout promises RGBA "
                               "(pass --allow-rgb to train on it as is)")
        print(f"warpnerf: warning: {first_path} has no alpha channel; images are used as is", file=sys.stderr)


def _check_like_first(img_path: str, shape, first_path: str, first_shape) -> None:
    """An image's (h, w, channels) against the first image's: same size, alpha in both or neither."""
    (h, w, c), (h0, w0, c0) = shape, first_shape
    if (h, w) != (h0, w0):
        raise DatasetError(f"image size mismatch: {img_path} is {w}x{h}, expected {w0}x{h0} like {first_path}")
    if (c == 4) != (c0 == 4):
        raise DatasetError(f"channel mismatch: {img_path} has {c} channels, {first_path} has {c0}")


def _check_depth_size(d_path: str, size, h0: int, w0: int) -> None:
    if tuple(size) != (h0, w0):
        raise DatasetError(f"depth size mismatch: {d_path} is {size[1]}x{size[0]}, expected {w0}x{h0}")


def _load_split(root: str, path: str, downscale: int, bg, keep_alpha: bool, allow_rgb: bool = False,
                pixels: bool = True) -> Views:
    meta = read_transforms(path)
    frames = meta["frames"]
    n = len(frames)
    paths = [_image_path(root, str(fr["file_path"])) for fr in frames]
    c2w = np.stack([np.asarray(fr["transform_matrix"], dtype=np.float32)[:3, :4] for fr in frames])

    has_depth = ["depth_path" in fr for fr in frames]
    if any(has_depth) and not all(has_depth):
        raise DatasetError(f"{path}: only some frames have 'depth_path' (frame {has_depth.index(False)} has none)")
    depth_scale = meta.get("depth_scale")

    if not pixels:
        return _cameras_only_split(root, path, meta, paths, c2w, downscale, keep_alpha, allow_rgb)
    first = read_image(paths[0])
    h0, w0 = first.shape[:2]
    _check_channels(paths[0], first.shape[-1], allow_rgb)
    h, w = h0 // downscale, w0 // downscale
    images = np.empty((n, h, w, 3), np.float32)
    alpha = np.empty((n, h, w), np.float32) if keep_alpha else None
    depth = np.empty((n, h, w), np.float32) if all(has_depth) else None
    bg = np.asarray(bg, np.float32)

    def load_one(i: int, img_path: str) -> None:
        img = first if i == 0 else read_image(img_path)
        _check_like_first(img_path, img.shape, paths[0], first.shape)
        rgb = img[..., :3] if img.shape[-1] >= 3 else np.repeat(img, 3, -1)
        a = img[..., 3] if img.shape[-1] == 4 else np.ones((h0, w0), np.float32)
        # Composite before downscaling: compositing is linear in (rgb * a, a), so the order
        # does not change the result, and one average of 3 channels is cheaper than of 4.
        images[i] = area_downscale(rgb * a[..., None] + bg * (1.0 - a[..., None]), downscale)
        if alpha is not None:
            alpha[i] = area_downscale(a, downscale)
        if depth is not None:
            d_path = os.path.normpath(os.path.join(root, str(frames[i]["depth_path"])))
            d = read_depth(d_path, depth_scale)
            _check_depth_size(d_path, d.shape, h0, w0)
            depth[i] = downscale_depth(d, downscale)

    load_parallel(paths, load_one)

    focal_full, cx_full, cy_full = _intrinsics(path, meta, w0, h0)
    return Views(
        images=torch.from_numpy(images),
        c2w=torch.from_numpy(c2w),
        focal=focal_full / downscale,
        cx=cx_full / downscale,
        cy=cy_full / downscale,
        ids=list(range(n)),
        depth=None if depth is None else torch.from_numpy(depth),
        alpha=None if alpha is None else torch.from_numpy(alpha),
    )


def _intrinsics(path: str, meta: dict, w0: int, h0: int) -> tuple[float, float, float]:
    """(focal, cx, cy) in pixels of the full-size (w0 x h0) images of one transforms file, checked."""
    if "fl_x" in meta:
        focal_full = json_number(path, "fl_x", meta["fl_x"], positive=True)
        cx_full = json_number(path, "cx", meta["cx"]) if "cx" in meta else w0 / 2
        cy_full = json_number(path, "cy", meta["cy"]) if "cy" in meta else h0 / 2
    else:
        angle = json_number(path, "camera_angle_x", meta["camera_angle_x"])
        if not 0.0 < angle < math.pi:
            raise DatasetError(f"{path}: 'camera_angle_x' must be in (0, pi) radians, got {angle}")
        focal_full = 0.5 * w0 / math.tan(0.5 * angle)
        cx_full, cy_full = w0 / 2, h0 / 2
    check_intrinsics(path, w0, h0, focal_full, focal_full, cx_full, cy_full)
    return focal_full, cx_full, cy_full


def _cameras_only_split(root: str, path: str, meta: dict, paths: list[str], c2w: np.ndarray, downscale: int,
                        keep_alpha: bool, allow_rgb: bool) -> Views:
    """:func:`_load_split` without a decoded pixel: sizes and channels from the image headers, the same
    checks and messages, stand-ins for the images, alpha and depth."""
    frames = meta["frames"]
    n = len(frames)
    has_depth = all("depth_path" in fr for fr in frames)
    heads = image_headers(paths)
    h0, w0, c0 = heads[0]
    _check_channels(paths[0], c0, allow_rgb)
    for img_path, shape in zip(paths, heads):
        _check_like_first(img_path, shape, paths[0], heads[0])
    h, w = downscaled_size(h0, w0, downscale)
    if has_depth:
        if meta.get("depth_scale") is None and any(not str(fr["depth_path"]).endswith(".npy") for fr in frames):
            bad = next(fr["depth_path"] for fr in frames if not str(fr["depth_path"]).endswith(".npy"))
            raise DatasetError(f"depth file {os.path.normpath(os.path.join(root, str(bad)))} is a PNG but the "
                               "transforms file has no 'depth_scale'")
        for fr in frames:
            d_path = os.path.normpath(os.path.join(root, str(fr["depth_path"])))
            _check_depth_size(d_path, depth_header(d_path), h0, w0)
    focal_full, cx_full, cy_full = _intrinsics(path, meta, w0, h0)
    return Views(
        images=stand_in((n, h, w, 3)),
        c2w=torch.from_numpy(c2w),
        focal=focal_full / downscale,
        cx=cx_full / downscale,
        cy=cy_full / downscale,
        ids=list(range(n)),
        depth=stand_in((n, h, w)) if has_depth else None,
        alpha=stand_in((n, h, w)) if keep_alpha else None,
    )
