"""Built-in procedural scenes: rendered once with Warp ray tracing, cached in the Blender layout.

A built-in scene needs no download: the first ``load_builtin("chair")`` renders 100 train,
100 val and 200 test views (Blender conventions: z-up world, ``camera_angle_x`` 0.6911,
cameras at radius 4.03 looking at the origin; train/val from fixed seeds on the upper
hemisphere, test on a 30° elevation orbit), writes them like a NeRF-synthetic scene and then
loads that folder with :func:`warpnerf.data.blender.load_blender`.

Cache layout (``$WARPNERF_CACHE``, else ``$XDG_CACHE_HOME/warpnerf``, else ``~/.cache/warpnerf``)::

    <cache>/scenes/chair_200px_g1/                 # <name>_<resolution>px_g<GENERATOR_VERSION>[_n<train>-<val>-<test>]
        transforms_{train,val,test}.json
        train/r_0.png  train/r_0_depth.png ...     # RGBA uint8; 16-bit depth, value / depth_scale = camera-z depth
        .complete                                  # JSON marker, written last
    <cache>/scenes/.tmp-chair_200px_g1-<pid>-<rand>/   # generation in progress

Generation writes into the temp folder, writes the marker, then renames it into place, so a
folder without the marker is never loaded: it is deleted and regenerated. Temp folders of
dead processes are removed. Bump GENERATOR_VERSION whenever the geometry, materials,
cameras or file format change, so stale caches are never reused.

Images are one ray per pixel centre (no antialiasing), so alpha is exactly 0 or 1 and depth is
exact; this also matches how NeRF renders a pixel (one ray through its centre).

The forward-facing scene (:data:`FORWARD_FACING`, ``yard``) is a hand-held-style capture of the
garden instead: 32 views from a small patch of positions, all looking the same way, written in
the LLFF layout (``images/000.png ...`` and ``poses_bounds.npy`` with each view's depth bounds)
and loaded by :func:`warpnerf.data.llff.load_llff`, so it trains in NDC like fern.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
import uuid

import numpy as np
import torch
from tqdm import tqdm

from warpnerf.data.blender import load_blender, read_depth, read_transforms
from warpnerf.data.builtin_meshes import SCENES, SceneMesh, garden_environment, garden_mesh
from warpnerf.data.errors import DatasetError
from warpnerf.data.images import load_parallel
from warpnerf.data.llff import load_llff
from warpnerf.data.scene import Scene
from warpnerf.device import init_warp, num_threads, run_chunks, split_range
from warpnerf.geometry import cameras
from warpnerf.geometry.rayspace import RaySpace

GENERATOR_VERSION = 1
DEFAULT_RESOLUTION = 200  # pixels (square): all 400 views render+write in ~5-7 s on 2 shared CPU cores
DEFAULT_COUNTS = (100, 100, 200)  # train, val, test views
CAMERA_ANGLE_X = 0.6911112070083618  # radians, the NeRF-synthetic value
CAMERA_RADIUS = 4.031128874149275  # sqrt(16.25), the NeRF-synthetic camera distance
TEST_ELEVATION_DEG = 30.0
DEPTH_SCALE = 5000.0  # depth PNG units per scene unit: 0.2 mm steps, up to 13.1 units
_SPLIT_SEEDS = {"train": 0, "val": 1}
_MARKER = ".complete"

# Lighting shared by every scene: a key light from the front-right above (with hard shadows),
# a weak fill from the back-left below, so no face is lit by the ambient term alone.
KEY_DIR = (0.42, -0.56, 0.71)
FILL_DIR = (-0.55, 0.70, -0.45)
KEY_STRENGTH, FILL_STRENGTH, AMBIENT = 0.62, 0.18, 0.30


# Unbounded built-in scenes: rendered by their own function, loaded with a contracted ray space
# (warpnerf.geometry.rayspace): the world is scaled by GARDEN_SCALE so the chair's box (+-1.5) lies in
# the unit ball; the cameras (radius 4.03) sit at 2.0, the ground's edge (8) at 4 and the
# environment sphere (15) at 7.5, i.e. contracted radii 1.5, 1.75 and 1.87.
UNBOUNDED = {
    "garden": "the chair on a veined stone ground inside a distant marbled environment: an unbounded 360° scene",
}
GARDEN_SCALE = 0.5
GARDEN_NEAR = 0.05  # normalised units (0.1 scene units)
GARDEN_DEPTH_SCALE = 3000.0  # the environment is up to ~19 units away: 16-bit depth up to 21.8 units

# Forward-facing built-in scenes: the garden photographed as LLFF scenes are (module doc)
FORWARD_FACING = {
    "yard": "the garden's chair from the front, a hand-held forward-facing capture (LLFF layout, NDC)",
}
FF_VIEWS = 32  # LLFF scenes hold 20-60 photos; every 8th is a test view (load_llff's holdout)
FF_RESOLUTION = 320  # image width in pixels; the height is 3/4 of it (fern's images_8: 504 x 378)
FF_SEED = 2
FF_ELEVATION_DEG = 12.0  # the central camera, seen from the chair's middle (FF_AIM): above the horizon
FF_AZIMUTH_DEG = -60.0
FF_DISTANCE = 4.8
FF_AIM = (0.0, 0.0, 0.2)
FF_SPREAD = (1.0, 0.5)  # the patch of camera centres: width and height in scene units (the chair ~1.2 wide)
FF_PERCENTILES = (0.1, 99.9)  # depth bounds per view, as LLFF takes them from COLMAP's points


def builtin_scenes() -> dict[str, str]:
    """Name -> one-line description of every built-in scene."""
    return {**{name: desc for name, (_, desc) in SCENES.items()}, **UNBOUNDED, **FORWARD_FACING}


def default_counts(name: str) -> tuple:
    """View counts of a built-in scene: (train, val, test) for object and unbounded scenes,
    (views,) for forward-facing ones (LLFF holds every 8th view out for testing)."""
    return (FF_VIEWS,) if name in FORWARD_FACING else DEFAULT_COUNTS


def _counts(name: str, counts) -> tuple:
    counts = default_counts(name) if counts is None else tuple(int(c) for c in counts)
    if len(counts) != len(default_counts(name)):
        kind = "(views,)" if name in FORWARD_FACING else "(train, val, test)"
        raise DatasetError(f"built-in scene '{name}' takes view counts {kind}, got {counts}")
    return counts


def default_resolution(name: str) -> int:
    """Image width of a built-in scene when none is asked for."""
    return FF_RESOLUTION if name in FORWARD_FACING else DEFAULT_RESOLUTION


def scene_mesh(name: str) -> SceneMesh:
    """The triangle mesh and materials of a built-in (bounded) scene."""
    if name not in SCENES:
        raise DatasetError(f"unknown built-in scene '{name}'; built-in scenes: {', '.join(SCENES)}")
    return SCENES[name][0]()


# ---- cameras ---------------------------------------------------------------------------------


def look_at(eyes: np.ndarray, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(N, 3, 4) float32 OpenGL camera-to-world matrices of cameras at ``eyes`` (N, 3) looking at ``target``.

    No roll: the camera x axis is horizontal (as in Blender's NeRF-synthetic renders). The numpy face
    of :func:`warpnerf.geometry.cameras.look_at` (computed in float64), so both treat a camera looking along
    ``up`` the same way.
    """
    c2w = cameras.look_at(torch.from_numpy(np.asarray(eyes, np.float64)), target, up)
    return c2w.numpy().astype(np.float32)


def hemisphere_cameras(n: int, seed: int, radius: float = CAMERA_RADIUS) -> np.ndarray:
    """(n, 3, 4) cameras at uniformly random directions on the upper hemisphere (z >= 0)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.0, 1.0, n)  # uniform z <=> uniform area on the hemisphere (Archimedes)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    s = np.sqrt(1.0 - z * z)
    return look_at(radius * np.stack([s * np.cos(phi), s * np.sin(phi), z], -1))


def orbit_cameras(n: int, elevation_deg: float = TEST_ELEVATION_DEG, radius: float = CAMERA_RADIUS) -> np.ndarray:
    """(n, 3, 4) cameras evenly spaced on a circle at fixed elevation (degrees above the horizon)."""
    phi = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    el = math.radians(elevation_deg)
    return look_at(radius * np.stack([math.cos(el) * np.cos(phi), math.cos(el) * np.sin(phi), np.full(n, math.sin(el))], -1))


def split_cameras(counts=DEFAULT_COUNTS) -> dict[str, np.ndarray]:
    """The (N, 3, 4) cameras of each split of every built-in scene."""
    n_train, n_val, n_test = counts
    return {
        "train": hemisphere_cameras(n_train, _SPLIT_SEEDS["train"]),
        "val": hemisphere_cameras(n_val, _SPLIT_SEEDS["val"]),
        "test": orbit_cameras(n_test),
    }


def forward_facing_cameras(n: int = FF_VIEWS, seed: int = FF_SEED) -> np.ndarray:
    """(n, 3, 4) cameras of a hand-held forward-facing capture of the garden's chair.

    Centres on a jittered grid over a FF_SPREAD patch facing the chair from FF_DISTANCE, all
    looking at one point 8 units beyond the chair (nearly parallel axes, as an LLFF capture), in
    a fixed random order so that every 8th view (the test views) lies anywhere in the patch, not
    along one edge."""
    rng = np.random.default_rng(seed)
    el, az = math.radians(FF_ELEVATION_DEG), math.radians(FF_AZIMUTH_DEG)
    forward = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    centre = np.asarray(FF_AIM) - FF_DISTANCE * forward
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    cols = max(int(round(math.sqrt(n * FF_SPREAD[0] / FF_SPREAD[1]))), 1)
    rows = -(-n // cols)
    k = rng.permutation(rows * cols)[:n]
    gx = ((k % cols) + 0.5 + rng.uniform(-0.3, 0.3, n)) / cols - 0.5
    gy = ((k // cols) + 0.5 + rng.uniform(-0.3, 0.3, n)) / rows - 0.5
    eyes = centre + np.outer(gx * FF_SPREAD[0], right) + np.outer(gy * FF_SPREAD[1], up)
    return look_at(eyes, target=tuple(np.asarray(FF_AIM) + 8.0 * forward))


def opengl_to_llff(c2w: np.ndarray) -> np.ndarray:
    """(N, 3, 4) OpenGL [right, up, back | t] -> LLFF [down, right, back | t]; the inverse of
    :func:`warpnerf.data.llff.llff_to_opengl`."""
    c2w = np.asarray(c2w, np.float64)
    return np.concatenate([-c2w[:, :, 1:2], c2w[:, :, 0:1], c2w[:, :, 2:4]], axis=2)


def focal_from_angle(width: int, camera_angle_x: float = CAMERA_ANGLE_X) -> float:
    """Focal length in pixels for a horizontal field of view in radians."""
    return 0.5 * width / math.tan(0.5 * camera_angle_x)


# ---- rendering -------------------------------------------------------------------------------


class MeshRenderer:
    """A scene mesh uploaded to Warp once, rendered from any cameras.

    Args:
        mesh: geometry + materials.
        device: Warp device. CPU by default so cached datasets are identical on any machine.
        shadows: trace a shadow ray towards the key light.
    """

    def __init__(self, mesh: SceneMesh, device: str = "cpu", shadows: bool = True):
        wp = init_warp()
        from warpnerf.kernels import raytrace  # lazy: imports Warp, which only generating a scene needs
        from warpnerf.ops.launch import load_here  # lazy: warpnerf.ops stays out of --help

        self._wp, self._kernel, self.device, self.shadows = wp, raytrace.render_mesh, device, shadows
        load_here(self._kernel, device)  # before the worker threads launch it
        arr = lambda x, dt: wp.array(x, dtype=dt, device=device)  # noqa: E731
        self._points = arr(mesh.points, wp.vec3)
        self._indices = arr(mesh.faces.reshape(-1), wp.int32)
        self._mesh = wp.Mesh(points=self._points, indices=self._indices)
        mats = mesh.materials
        self._tables = [
            self._indices,
            arr(mesh.normals, wp.vec3),
            arr(mesh.face_material, wp.int32),
            arr(np.array([m.pattern for m in mats], np.int32), wp.int32),
            arr(np.array([m.color_a for m in mats], np.float32), wp.vec3),
            arr(np.array([m.color_b for m in mats], np.float32), wp.vec3),
            arr(np.array([m.freq for m in mats], np.float32), wp.float32),
            arr(np.array([m.axis for m in mats], np.int32), wp.int32),
            arr(np.array([m.origin for m in mats], np.float32), wp.vec3),
        ]

    def render(self, c2w: np.ndarray, width: int, height: int, focal: float) -> tuple[np.ndarray, np.ndarray]:
        """Render views; returns rgba (N, H, W, 4) float32 in [0, 1] (straight alpha, exactly 0/1)
        and depth (N, H, W) float32 camera-z distance in scene units, 0 where the ray misses.

        ``c2w`` is (N, 3, 4) OpenGL; the principal point is the image centre. On CPU the views
        are split over the worker threads (each launch runs on one thread).
        """
        from warpnerf.ops.launch import launch  # lazy: warpnerf.ops stays out of --help

        wp = self._wp
        c2w = np.asarray(c2w, np.float32).reshape(-1, 3, 4)
        n = len(c2w)
        rgba = np.empty((n, height, width, 4), np.float32)
        depth = np.empty((n, height, width), np.float32)
        norm = lambda v: wp.vec3(*(np.asarray(v) / np.linalg.norm(v)))  # noqa: E731

        def task(lo: int, hi: int):
            def run():
                out_rgba = wp.empty((hi - lo, height, width), dtype=wp.vec4, device=self.device)
                out_depth = wp.empty((hi - lo, height, width), dtype=wp.float32, device=self.device)
                # Warp-made arrays: the shared launcher runs it on Warp's stream for this device
                launch(
                    self._kernel,
                    (hi - lo, height, width),
                    [
                        self._mesh.id,
                        *self._tables,
                        wp.array(np.ascontiguousarray(c2w[lo:hi, :, :3]), dtype=wp.mat33, device=self.device),
                        wp.array(np.ascontiguousarray(c2w[lo:hi, :, 3]), dtype=wp.vec3, device=self.device),
                        float(focal),
                        width / 2.0,
                        height / 2.0,
                        norm(KEY_DIR),
                        KEY_STRENGTH,
                        norm(FILL_DIR),
                        FILL_STRENGTH,
                        AMBIENT,
                        int(self.shadows),
                    ],
                    self.device,
                    outputs=[out_rgba, out_depth],
                )
                rgba[lo:hi] = out_rgba.numpy().reshape(hi - lo, height, width, 4)
                depth[lo:hi] = out_depth.numpy()

            return run

        threads = num_threads() if self.device == "cpu" else 1
        run_chunks([task(lo, hi) for lo, hi in split_range(n, threads) if hi > lo])
        return rgba, depth


# ---- cache -----------------------------------------------------------------------------------


def cache_root(cache_dir: str | None = None) -> str:
    """Folder holding generated scenes: ``cache_dir``, ``$WARPNERF_CACHE``, ``$XDG_CACHE_HOME/warpnerf``
    or ``~/.cache/warpnerf`` (first one set), plus ``/scenes``."""
    base = cache_dir or os.environ.get("WARPNERF_CACHE")
    if not base:
        xdg = os.environ.get("XDG_CACHE_HOME")
        base = os.path.join(xdg, "warpnerf") if xdg else os.path.join(os.path.expanduser("~"), ".cache", "warpnerf")
    return os.path.join(os.path.abspath(os.path.expanduser(base)), "scenes")


def cache_key(name: str, resolution: int, counts=None) -> str:
    counts = _counts(name, counts)
    key = f"{name}_{resolution}px_g{GENERATOR_VERSION}"
    if counts != default_counts(name):
        key += "_n" + "-".join(str(c) for c in counts)
    return key


def is_complete(folder: str) -> bool:
    """True when ``folder`` holds a finished generation (its marker exists and parses)."""
    try:
        with open(os.path.join(folder, _MARKER), encoding="utf-8") as f:
            return json.load(f).get("generator_version") == GENERATOR_VERSION
    except (OSError, ValueError):
        return False


def _cache_error(path: str, exc: OSError | str) -> DatasetError:
    why = exc if isinstance(exc, str) else (exc.strerror or str(exc))
    return DatasetError(
        f"built-in scene cache {path} is not usable ({why}); set WARPNERF_CACHE to a writable folder"
    )


def ensure_builtin(
    name: str,
    resolution: int | None = None,
    cache_dir: str | None = None,
    counts=None,
    progress: bool = True,
) -> str:
    """Generate the built-in scene if its cache folder is missing or incomplete; returns the folder.
    ``counts``: see :func:`default_counts` (None: the scene's default)."""
    if name not in builtin_scenes():
        raise DatasetError(f"unknown built-in scene '{name}'; built-in scenes: {', '.join(SCENES)}")
    counts = _counts(name, counts)
    resolution = int(resolution or default_resolution(name))
    if resolution < 1:
        raise DatasetError(f"resolution must be a positive number of pixels, got {resolution}")
    root = cache_root(cache_dir)
    final = os.path.join(root, cache_key(name, resolution, counts))
    if is_complete(final):
        if not os.access(final, os.R_OK | os.X_OK):
            raise _cache_error(final, "not readable")
        return final
    try:
        os.makedirs(root, exist_ok=True)
        _remove_stale_temps(root, cache_key(name, resolution, counts))
        if os.path.exists(final):  # a folder without its marker: interrupted or tampered with
            shutil.rmtree(final)
        tmp = os.path.join(root, f".tmp-{cache_key(name, resolution, counts)}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
        os.makedirs(tmp)
    except OSError as exc:
        raise _cache_error(root, exc) from None
    try:
        generate_builtin(name, tmp, resolution, counts, progress)
        try:
            os.rename(tmp, final)
        except OSError:
            if not is_complete(final):  # another process finished first: theirs is as good as ours
                raise
    except OSError as exc:
        raise _cache_error(root, exc) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


def _remove_stale_temps(root: str, key: str) -> None:
    """Delete temp folders of ``key`` left by processes that no longer exist."""
    prefix = f".tmp-{key}-"
    for entry in os.listdir(root):
        if not entry.startswith(prefix):
            continue
        try:
            pid = int(entry[len(prefix) :].split("-")[0])
            os.kill(pid, 0)
            continue  # still running: maybe another process generating the same scene
        except (ValueError, ProcessLookupError):
            pass
        except PermissionError:
            continue  # exists, owned by someone else
        shutil.rmtree(os.path.join(root, entry), ignore_errors=True)


def generate_builtin(name: str, out_dir: str, resolution: int | None = None, counts=None, progress: bool = True) -> None:
    """Render a built-in scene into ``out_dir`` in the Blender layout (forward-facing scenes: the
    LLFF layout, :func:`generate_forward_facing`), marker file last."""
    counts = _counts(name, counts)
    resolution = int(resolution or default_resolution(name))
    if name in FORWARD_FACING:
        generate_forward_facing(name, out_dir, resolution, counts[0], progress)
        return
    from PIL import Image  # lazy: codecs stay out of --help (~0.08 s)

    t0 = time.time()
    if name in UNBOUNDED:
        renderer, depth_scale = GardenRenderer(), GARDEN_DEPTH_SCALE
    else:
        renderer, depth_scale = MeshRenderer(scene_mesh(name)), DEPTH_SCALE
    width = height = resolution
    focal = focal_from_angle(width)
    cams = split_cameras(counts)
    bar = tqdm(
        total=sum(len(c) for c in cams.values()),
        desc=f"rendering built-in scene '{name}' at {width}x{height}",
        unit="view",
        disable=not progress,
    )
    batch = 20  # views per render call: bounds memory and keeps the progress bar moving
    with bar:
        for split, c2w in cams.items():
            os.makedirs(os.path.join(out_dir, split), exist_ok=True)
            frames = []
            for start in range(0, len(c2w), batch):
                rgba, depth = renderer.render(c2w[start : start + batch], width, height, focal)
                rgba8 = np.round(rgba * 255.0).astype(np.uint8)
                if depth.max() * depth_scale > 65535:
                    raise DatasetError(f"depth {depth.max():.2f} does not fit the 16-bit depth PNG of scene '{name}'")
                depth16 = np.round(depth * depth_scale).astype(np.uint16)

                def write(k: int, stem: str, rgba8=rgba8, depth16=depth16) -> None:  # this batch's arrays
                    # compress_level 3: ~2x faster than the default 6 for a few % larger files.
                    Image.fromarray(rgba8[k], "RGBA").save(os.path.join(out_dir, stem + ".png"), compress_level=3)
                    Image.fromarray(depth16[k]).save(os.path.join(out_dir, stem + "_depth.png"), compress_level=3)

                stems = [f"{split}/r_{start + k}" for k in range(len(rgba))]
                load_parallel(stems, write, threads=2)
                for k, stem in enumerate(stems):
                    frames.append(
                        {
                            "file_path": f"./{stem}",
                            "depth_path": f"./{stem}_depth.png",
                            "transform_matrix": np.vstack([c2w[start + k], [0, 0, 0, 1]]).tolist(),
                        }
                    )
                bar.update(len(rgba))
            meta = {
                "camera_angle_x": CAMERA_ANGLE_X,
                "depth_scale": depth_scale,
                "warpnerf": {"scene": name, "generator_version": GENERATOR_VERSION, "resolution": resolution},
                "frames": frames,
            }
            with open(os.path.join(out_dir, f"transforms_{split}.json"), "w", encoding="utf-8") as f:
                json.dump(meta, f, indent=1)
    _write_marker(out_dir, name, resolution, counts, t0)


def _write_marker(out_dir: str, name: str, resolution: int, counts, t0: float) -> None:
    """The marker that makes a generated folder complete (:func:`is_complete`); written last."""
    marker = {
        "generator_version": GENERATOR_VERSION,
        "scene": name,
        "resolution": resolution,
        "counts": list(counts),
        "seconds": round(time.time() - t0, 2),
    }
    with open(os.path.join(out_dir, _MARKER), "w", encoding="utf-8") as f:
        json.dump(marker, f)


def generate_forward_facing(name: str, out_dir: str, width: int = FF_RESOLUTION, n_views: int = FF_VIEWS,
                            progress: bool = True) -> None:
    """Render forward-facing scene ``name`` into ``out_dir`` in the LLFF layout, marker file last:
    ``images/000.png ...`` (RGB, every pixel covered) and ``poses_bounds.npy`` ((N, 17): the LLFF
    [down, right, back | centre | height, width, focal] matrix and the 0.1 / 99.9 percentiles of
    the view's depth, :data:`FF_PERCENTILES`)."""
    from PIL import Image  # lazy: codecs stay out of --help (~0.08 s)

    t0 = time.time()
    height = max(int(round(width * 0.75)), 1)
    focal = focal_from_angle(width)
    c2w = forward_facing_cameras(n_views)
    # each view's row of poses_bounds.npy: the LLFF pose with (height, width, focal) as a 5th column
    hwf = np.tile(np.array([[height], [width], [focal]], np.float64), (n_views, 1, 1))
    poses = np.concatenate([opengl_to_llff(c2w), hwf], axis=2).reshape(n_views, 15)
    renderer = GardenRenderer()
    os.makedirs(os.path.join(out_dir, "images"), exist_ok=True)
    bounds = []
    batch = 8
    with tqdm(total=n_views, desc=f"rendering built-in scene '{name}' at {width}x{height}", unit="view",
              disable=not progress) as bar:
        for start in range(0, n_views, batch):
            rgba, depth = renderer.render(c2w[start:start + batch], width, height, focal)
            rgb8 = np.round(rgba[..., :3] * 255.0).astype(np.uint8)

            def write(k: int, path: str, rgb8=rgb8) -> None:  # this batch's array
                Image.fromarray(rgb8[k], "RGB").save(path, compress_level=3)

            paths = [os.path.join(out_dir, "images", f"{start + k:03d}.png") for k in range(len(rgb8))]
            load_parallel(paths, write, threads=2)
            for k in range(len(rgb8)):
                bounds.append(np.percentile(depth[k][depth[k] > 0], FF_PERCENTILES))
            bar.update(len(rgb8))
    np.save(os.path.join(out_dir, "poses_bounds.npy"), np.concatenate([poses, np.stack(bounds)], axis=1))
    _write_marker(out_dir, name, width, (n_views,), t0)


def load_builtin(
    name: str,
    resolution: int | None = None,
    cache_dir: str | None = None,
    downscale: int = 1,
    splits: tuple[str, ...] = ("train", "val", "test"),
    white_background: bool = True,
    counts=None,
    progress: bool = True,
    pixels: bool = True,
) -> Scene:
    """Generate (once) and load a built-in scene (source "builtin", kind "blender"; the unbounded
    ones, :data:`UNBOUNDED`, kind "unbounded" with a contracted ray space; the forward-facing
    ones, :data:`FORWARD_FACING`, kind "llff" with LLFF's NDC ray space, train and test views only).

    Args:
        name: one of :func:`builtin_scenes`.
        resolution: image side in pixels (default DEFAULT_RESOLUTION); each resolution is cached apart.
        cache_dir: overrides ``$WARPNERF_CACHE``.
        downscale, splits, white_background: as in :func:`warpnerf.data.blender.load_blender`.
        counts: (train, val, test) view counts; the defaults follow NeRF-synthetic (100, 100, 200).
            Forward-facing scenes: (views,), default (FF_VIEWS,).
        progress: show a tqdm bar while generating.
        pixels: False: a cameras-only load (:mod:`warpnerf.data.scene`) of the cached files (a scene not
            cached yet is generated first).
    """
    folder = ensure_builtin(name, resolution, cache_dir, counts, progress)
    if name in FORWARD_FACING:
        scene = load_llff(folder, factor=1, downscale=downscale, name=name, pixels=pixels)
        scene.source = "builtin"
        return scene
    scene = load_blender(folder, downscale=downscale, splits=splits, white_background=white_background, name=name,
                         pixels=pixels)
    scene.source = "builtin"
    if name in UNBOUNDED:
        scene.kind = "unbounded"
        scene.ray_space = RaySpace.contracted(GARDEN_NEAR, scale=GARDEN_SCALE)
    return scene


# ---- the built-in scenes written out in capture layouts (test data nobody downloads) ------------

EXPORT_LAYOUTS = ("colmap-text", "colmap-binary", "transforms")


def export_builtin(
    name: str,
    out_dir: str,
    layout: str,
    resolution: int | None = None,
    cache_dir: str | None = None,
    counts=None,
    points_per_view: int = 200,
    progress: bool = True,
) -> str:
    """Write built-in scene ``name`` as a capture in ``layout``; returns ``out_dir``.

    Layouts (what :func:`warpnerf.data.colmap.load_colmap` and
    :func:`warpnerf.data.transforms_json.load_transforms_json` read):

    * ``colmap-text`` / ``colmap-binary``: ``images/<split>_r_<k>.png``, ``sparse/0/cameras,
      images, points3D`` (.txt / .bin; one SIMPLE_PINHOLE camera) and ``{train,val,test}_list.txt``;
    * ``transforms``: the same images and one ``transforms.json`` with ``fl_x``/``fl_y``/``cx``/``cy``/
      ``w``/``h`` and ``{train,val,test}_filenames``.

    Images are the cached Blender-layout PNGs, byte for byte, and the poses the same cameras, so
    each layout loads the same views as :func:`load_builtin` up to the documented normalisation.
    The sparse points are depth-map back-projections of ``points_per_view`` random foreground
    pixels of each training view (fixed seed), observed by that view only.
    """
    if layout not in EXPORT_LAYOUTS:
        raise DatasetError(f"unknown export layout '{layout}'; choose one of {', '.join(EXPORT_LAYOUTS)}")
    if name in FORWARD_FACING:
        raise DatasetError(f"built-in scene '{name}' is already a capture in the LLFF layout: "
                           f"{ensure_builtin(name, resolution, cache_dir, counts, progress)}")
    from PIL import Image  # lazy: codecs stay out of --help (~0.08 s)

    src = ensure_builtin(name, resolution, cache_dir, counts, progress)
    img_dir = os.path.join(out_dir, "images")
    os.makedirs(img_dir, exist_ok=True)
    frames, lists = [], {}
    width = height = None
    for split in ("train", "val", "test"):
        meta = read_transforms(os.path.join(src, f"transforms_{split}.json"))
        lists[split] = []
        for k, fr in enumerate(meta["frames"]):
            stem = os.path.normpath(os.path.join(src, fr["file_path"]))
            out_name = f"{split}_r_{k}.png"
            shutil.copyfile(stem + ".png", os.path.join(img_dir, out_name))
            depth = read_depth(os.path.normpath(os.path.join(src, fr["depth_path"])), meta["depth_scale"])
            height, width = depth.shape
            c2w = np.asarray(fr["transform_matrix"], np.float64)[:3, :4]
            frames.append((split, out_name, c2w, depth, stem + ".png"))
            lists[split].append(out_name)
    focal = focal_from_angle(width)
    cx, cy = width / 2.0, height / 2.0

    if layout == "transforms":
        meta = {
            "camera_model": "OPENCV",
            "fl_x": focal, "fl_y": focal, "cx": cx, "cy": cy, "w": width, "h": height,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "frames": [{"file_path": f"images/{n}", "transform_matrix": np.vstack([m, [0, 0, 0, 1]]).tolist()}
                       for _, n, m, _, _ in frames],
            **{f"{s}_filenames": [f"images/{n}" for n in lists[s]] for s in lists},
            "warpnerf": {"scene": name, "generator_version": GENERATOR_VERSION, "resolution": width},
        }
        with open(os.path.join(out_dir, "transforms.json"), "w", encoding="utf-8") as f:
            json.dump(meta, f, indent=1)
        return out_dir

    from warpnerf.data import colmap as cm  # lazy: the COLMAP reader stays out of --help

    rng = np.random.default_rng(0)
    cameras = {1: cm.Camera(1, "SIMPLE_PINHOLE", width, height, np.array([focal, cx, cy]))}
    images, points = {}, {}
    for iid, (split, out_name, c2w, depth, png) in enumerate(frames, start=1):
        q, t = cm.c2w_to_colmap(c2w)
        xys, pids = np.zeros((0, 2)), np.zeros(0, np.int64)
        if split == "train":
            rows, cols = np.nonzero(depth > 0)
            pick = rng.choice(len(rows), size=min(points_per_view, len(rows)), replace=False)
            rows, cols = rows[pick], cols[pick]
            u, v, z = cols + 0.5, rows + 0.5, depth[rows, cols].astype(np.float64)
            cam = np.stack([(u - cx) / focal * z, -(v - cy) / focal * z, -z], 1)  # OpenGL camera axes
            world = cam @ c2w[:, :3].T + c2w[:, 3]
            rgb = np.asarray(Image.open(png).convert("RGB"))[rows, cols]
            first = len(points) + 1
            pids = np.arange(first, first + len(world), dtype=np.int64)
            xys = np.stack([u, v], 1)
            for j, pid in enumerate(pids):
                points[int(pid)] = cm.Point3D(int(pid), world[j], rgb[j], 0.5, np.array([iid]), np.array([j]))
        images[iid] = cm.Image(iid, q, t, 1, out_name, xys, pids)
    ext = ".txt" if layout == "colmap-text" else ".bin"
    cm.write_model(os.path.join(out_dir, "sparse", "0"), cameras, images, points, ext)
    for split, names in lists.items():
        with open(os.path.join(out_dir, f"{split}_list.txt"), "w", encoding="utf-8") as f:
            f.write("".join(n + "\n" for n in names))
    return out_dir


class GardenRenderer:
    """The unbounded ``garden`` layout (chair on a textured ground inside a textured environment
    sphere, :func:`warpnerf.data.builtin_meshes.garden_mesh`), both meshes uploaded once.

    Two layers with the unchanged Warp tracer: the foreground with shadows, the environment
    without (a shadow ray would always hit the enclosing sphere); per pixel the nearer hit wins.
    """

    def __init__(self):
        self.fg = MeshRenderer(garden_mesh())
        self.env = MeshRenderer(garden_environment(), shadows=False)

    def render(self, c2w: np.ndarray, width: int, height: int, focal: float) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3, 4) cameras -> rgba (N, H, W, 4) float32 with alpha 1 (every pixel is covered) and
        camera-z depth (N, H, W), like :meth:`MeshRenderer.render`."""
        fg_rgba, fg_depth = self.fg.render(c2w, width, height, focal)
        env_rgba, env_depth = self.env.render(c2w, width, height, focal)
        use_fg = (fg_depth > 0) & ((fg_depth < env_depth) | (env_depth <= 0))
        rgb = np.where(use_fg[..., None], fg_rgba[..., :3], env_rgba[..., :3])
        rgba = np.concatenate([rgb, np.ones_like(rgb[..., :1])], -1)
        return rgba.astype(np.float32), np.where(use_fg, fg_depth, env_depth).astype(np.float32)


def render_garden(c2w: np.ndarray, width: int, height: int, focal: float) -> tuple[np.ndarray, np.ndarray]:
    """Render the ``garden`` layout (:class:`GardenRenderer`) from (N, 3, 4) cameras.
    Returns rgb (N, H, W, 3) float32 (every pixel is covered) and camera-z depth (N, H, W)."""
    rgba, depth = GardenRenderer().render(c2w, width, height, focal)
    return rgba[..., :3], depth
