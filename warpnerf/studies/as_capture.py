"""A Blender-layout dataset written out as a user's capture would arrive: RGB photos (alpha composited
on a background colour, then dropped) with a COLMAP text model without sparse points, or one
instant-ngp/nerfstudio ``transforms.json``. Issue #63's comparison: the same images through the
Blender loader and through the capture loaders, which must frame the object and detect the background
from the cameras and pixels alone.

    python -m warpnerf.studies.as_capture /work/shared/data/nerf_synthetic/lego /tmp/cap/legocap colmap-text
    python -m warpnerf.studies.as_capture /work/shared/data/nerf_synthetic/lego /tmp/cap/legotj transforms
    warpnerf train --scene legocap --data-root /tmp/cap --task full

Both layouts keep the dataset's train/val/test split (``{split}_list.txt`` / ``{split}_filenames``)
and its cameras exactly (one PINHOLE camera from ``camera_angle_x``).
"""

from __future__ import annotations

import argparse
import json
import math
import os

import numpy as np

from warpnerf.data import colmap as cm
from warpnerf.data.blender import read_transforms

LAYOUTS = ("colmap-text", "colmap-binary", "transforms")
SPLITS = ("train", "val", "test")


def rgb_on(rgba: np.ndarray, background: float) -> np.ndarray:
    """uint8 (H, W, 3) of a uint8 (H, W, 4) image composited on a grey level ``background`` in [0, 1]."""
    a = rgba[..., 3:4].astype(np.float64) / 255.0
    rgb = rgba[..., :3].astype(np.float64) * a + 255.0 * background * (1.0 - a)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def export_as_capture(src: str, out_dir: str, layout: str, background: float = 1.0) -> str:
    """Write the Blender-layout scene in ``src`` to ``out_dir`` in ``layout``; returns ``out_dir``."""
    from PIL import Image  # lazy, as in warpnerf.data

    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    img_dir = os.path.join(out_dir, "images")
    os.makedirs(img_dir, exist_ok=True)
    frames, lists, size, angle = [], {}, None, None
    for split in SPLITS:
        path = os.path.join(src, f"transforms_{split}.json")
        if not os.path.exists(path):
            continue
        meta = read_transforms(path)
        angle = float(meta["camera_angle_x"])
        lists[split] = []
        for k, fr in enumerate(meta["frames"]):
            png = os.path.normpath(os.path.join(src, fr["file_path"]))
            png = png if png.endswith(".png") else png + ".png"
            rgba = np.asarray(Image.open(png).convert("RGBA"))
            size = rgba.shape[1], rgba.shape[0]
            name = f"{split}_r_{k}.png"
            Image.fromarray(rgb_on(rgba, background)).save(os.path.join(img_dir, name))
            frames.append((name, np.asarray(fr["transform_matrix"], np.float64)[:3, :4]))
            lists[split].append(name)
    width, height = size
    focal = 0.5 * width / math.tan(0.5 * angle)
    cx, cy = width / 2.0, height / 2.0
    if layout == "transforms":
        meta = {"camera_model": "PINHOLE", "fl_x": focal, "fl_y": focal, "cx": cx, "cy": cy, "w": width, "h": height,
                "frames": [{"file_path": f"images/{n}", "transform_matrix": np.vstack([m, [0, 0, 0, 1]]).tolist()}
                           for n, m in frames],
                **{f"{s}_filenames": [f"images/{n}" for n in names] for s, names in lists.items()}}
        with open(os.path.join(out_dir, "transforms.json"), "w", encoding="utf-8") as f:
            json.dump(meta, f, indent=1)
        return out_dir
    cameras = {1: cm.Camera(1, "PINHOLE", width, height, np.array([focal, focal, cx, cy]))}
    images = {}
    for iid, (name, c2w) in enumerate(frames, start=1):
        q, t = cm.c2w_to_colmap(c2w)
        images[iid] = cm.Image(iid, q, t, 1, name, np.zeros((0, 2)), np.zeros(0, np.int64))
    cm.write_model(os.path.join(out_dir, "sparse", "0"), cameras, images, {}, ".txt" if layout == "colmap-text" else ".bin")
    for split, names in lists.items():
        with open(os.path.join(out_dir, f"{split}_list.txt"), "w", encoding="utf-8") as f:
            f.write("".join(n + "\n" for n in names))
    return out_dir


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("src", help="a Blender-layout scene folder (transforms_{train,val,test}.json)")
    p.add_argument("out", help="the capture folder to write (its name is the scene name)")
    p.add_argument("layout", choices=LAYOUTS)
    p.add_argument("--background", type=float, default=1.0, help="grey level the alpha is composited on (1 = white)")
    a = p.parse_args(argv)
    print(export_as_capture(a.src, a.out, a.layout, a.background))


if __name__ == "__main__":
    main()
