"""Camera paths and videos of a trained field: ``warpnerf render`` and the run's own video.

A camera path is a :class:`CameraPath`: (N, 3, 4) OpenGL camera-to-world matrices plus pinhole
intrinsics shared by all frames. Paths are built in the frame the field was trained in: for
the pose task that is the frame of the *optimised* training cameras, so an orbit built from
them looks at the reconstruction (test cameras are mapped into it with the training-camera
Sim(3) alignment, without photometric refinement).

Paths:

* ``orbit``: one turn about the scene's up axis (the mean of the training cameras' up vectors)
  around the point the training cameras look at, at their mean distance and elevation;
* ``spiral``: forward-facing scenes (``scene.ray_space.forward_facing``: LLFF) get LLFF's spiral
  about the average camera (two turns, radii from the 90th percentile of camera offsets, focus
  depth from the LLFF recipe); object-centric scenes get MipNeRF-360's ellipse-style path: one
  turn about the up axis whose elevation swings between the training cameras' low and high
  elevations;
* ``test``: the test cameras themselves (each at most once: no repeated frames);
* ``FILE.json``: a nerfstudio ``camera_path.json`` (``camera_path[i].camera_to_world`` as 16
  row-major floats, vertical ``fov`` in degrees, ``render_width``/``render_height``), read in the
  scene's own world frame.

Videos are MP4 (H.264 through ``imageio-ffmpeg``, which ships its own ffmpeg binary: ``pip install
warpnerf[video]``); without it the same frames are written as a GIF next to the requested path.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from dataclasses import dataclass

import imageio.v2 as imageio
import numpy as np
import torch
from tqdm.auto import tqdm

from warpnerf.geometry.cameras import look_at
from warpnerf.train.evaluate import depth_to_rgb
from warpnerf.train.memory import over_budget, render_bytes
from warpnerf.train.views import test_cameras, training_cameras

PATHS = ("orbit", "spiral", "test")


class PathError(ValueError):
    """A bad camera-path request or file (one line)."""


@dataclass
class CameraPath:
    c2w: torch.Tensor  # (N, 3, 4) float32, OpenGL convention (x right, y up, looking down -z)
    height: int  # pixels
    width: int
    focal: float  # pixels
    cx: float
    cy: float

    def __len__(self) -> int:
        return int(self.c2w.shape[0])


# ---- geometry helpers ------------------------------------------------------------------------


def scene_up(c2w: torch.Tensor) -> torch.Tensor:
    """Unit up vector (3,): the mean of the cameras' +y axes (Blender scenes: close to +z)."""
    up = c2w[:, :, 1].double().mean(0)
    return up / up.norm().clamp_min(1e-12)


def look_target(c2w: torch.Tensor) -> torch.Tensor:
    """(3,) the point closest (least squares) to all optical axes; for cameras that all look in
    about the same direction (no unique solution) the centroid moved along the mean view axis."""
    o = c2w[:, :, 3].double()
    d = -c2w[:, :, 2].double()
    d = d / d.norm(dim=-1, keepdim=True)
    eye = torch.eye(3, dtype=torch.float64)
    proj = eye[None] - d[:, :, None] * d[:, None, :]  # projector orthogonal to each axis
    a, b = proj.sum(0), (proj @ o[:, :, None]).sum(0)[:, 0]
    if torch.linalg.matrix_rank(a, rtol=1e-3) < 3:
        return o.mean(0) + d.mean(0)
    return torch.linalg.solve(a, b)


def _look_at(eyes: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    return look_at(eyes.double(), target=tuple(target.tolist()), up=tuple(up.tolist())).float()


def _orbit_frame(up: torch.Tensor):
    """Two unit vectors (3,) spanning the plane orthogonal to ``up``."""
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    if abs(float(helper @ up)) > 0.9:
        helper = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    e1 = helper - (helper @ up) * up
    e1 = e1 / e1.norm()
    return e1, torch.linalg.cross(up, e1)


def orbit_path(train_c2w: torch.Tensor, n: int, elevation_swing: bool = False) -> torch.Tensor:
    """(n, 3, 4) cameras on one turn about the scene's up axis through the look-at target.

    Radius and elevation are the training cameras' means; the turn starts at the first
    training camera's azimuth. ``elevation_swing``: the elevation oscillates (two periods per
    turn) between the 10th and 90th percentile of the training elevations (the object-centric
    "spiral", after MipNeRF-360's ellipse path)."""
    up, target = scene_up(train_c2w), look_target(train_c2w)
    rel = train_c2w[:, :, 3].double() - target
    dist = rel.norm(dim=-1)
    elev = torch.asin((rel @ up / dist).clamp(-1, 1))
    e1, e2 = _orbit_frame(up)
    az0 = math.atan2(float(rel[0] @ e2), float(rel[0] @ e1))
    theta = az0 + torch.linspace(0, 2 * math.pi, n + 1, dtype=torch.float64)[:-1]
    if elevation_swing:
        lo, hi = torch.quantile(elev, 0.1), torch.quantile(elev, 0.9)
        el = 0.5 * (lo + hi) + 0.5 * (hi - lo) * torch.sin(2 * (theta - az0))
    else:
        el = torch.full_like(theta, float(elev.mean()))
    r = float(dist.mean())
    dirs = (torch.cos(el)[:, None] * (torch.cos(theta)[:, None] * e1 + torch.sin(theta)[:, None] * e2)
            + torch.sin(el)[:, None] * up)
    return _look_at(target + r * dirs, target, up)


def llff_spiral_path(train_c2w: torch.Tensor, n: int, focus_depth: float, rots: float = 2.0,
                     zrate: float = 0.5) -> torch.Tensor:
    """(n, 3, 4) LLFF's ``render_path_spiral`` about the average camera.

    The camera centre moves on an ellipse (radii: 90th percentile of |camera offsets| in the
    average camera's frame) that also moves back and forth along the view axis (``zrate``),
    ``rots`` turns; every frame looks at the point ``focus_depth`` in front of the average camera."""
    c2w = train_c2w.double()
    center = c2w[:, :, 3].mean(0)
    z = c2w[:, :, 2].sum(0)
    z = z / z.norm()
    up = c2w[:, :, 1].sum(0)
    x = torch.linalg.cross(up, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    rot = torch.stack([x, y, z], -1)  # average camera's axes as columns
    local = (c2w[:, :, 3] - center) @ rot
    rads = torch.quantile(local.abs(), 0.9, dim=0)
    theta = torch.linspace(0, 2 * math.pi * rots, n + 1, dtype=torch.float64)[:-1]
    offs = torch.stack([torch.cos(theta), -torch.sin(theta), -torch.sin(theta * zrate)], -1) * rads
    eyes = center + offs @ rot.T
    target = center - focus_depth * z
    out = []
    for e in eyes:  # each frame looks at the same focus point with the average up
        out.append(_look_at(e[None], target, y)[0])
    return torch.stack(out)


def read_camera_path_json(path: str, default_size: tuple[int, int]) -> CameraPath:
    """A nerfstudio ``camera_path.json`` -> :class:`CameraPath` (world frame = the scene's)."""
    try:
        with open(path) as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise PathError(f"camera path file not found: {path}") from None
    except json.JSONDecodeError as e:
        raise PathError(f"{path}: not valid JSON: {e}") from None
    frames = data.get("camera_path") if isinstance(data, dict) else None
    if not frames:
        raise PathError(f"{path}: no 'camera_path' list (expected a nerfstudio camera_path.json)")
    if data.get("camera_type", "perspective") != "perspective":
        raise PathError(f"{path}: camera_type '{data['camera_type']}' is not supported (perspective only)")
    h = int(data.get("render_height", default_size[0]))
    w = int(data.get("render_width", default_size[1]))
    mats, fovs = [], []
    for i, f in enumerate(frames):
        m = np.asarray(f.get("camera_to_world", []), dtype=np.float64)
        if m.size != 16:
            raise PathError(f"{path}: camera_path[{i}].camera_to_world must have 16 numbers, got {m.size}")
        mats.append(m.reshape(4, 4)[:3])
        fovs.append(float(f.get("fov", data.get("fov", 50.0))))
    # one focal for the whole video (nerfstudio allows per-frame fov; we use the first frame's)
    focal = 0.5 * h / math.tan(math.radians(fovs[0]) / 2)
    return CameraPath(torch.as_tensor(np.stack(mats), dtype=torch.float32), h, w, focal, w / 2, h / 2)


def write_camera_path_json(path: str, cams: CameraPath, fps: float = 24.0) -> None:
    """Write ``cams`` as a nerfstudio-style ``camera_path.json`` (readable by ``--path FILE``)."""
    fov = math.degrees(2 * math.atan(0.5 * cams.height / cams.focal))
    rows = [torch.cat([c.double(), torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)]).reshape(-1).tolist()
            for c in cams.c2w]
    data = {"camera_type": "perspective", "render_height": cams.height, "render_width": cams.width, "fps": fps,
            "seconds": len(cams) / fps, "camera_path": [{"camera_to_world": r, "fov": fov, "aspect": cams.width / cams.height}
                                                         for r in rows]}
    with open(path, "w") as fh:
        json.dump(data, fh)


# ---- paths of a trained run ------------------------------------------------------------------


# LLFF spiral focus depth (forward-facing scenes): 1 / ((1 - 0.75) / close + 0.75 / inf) with LLFF's
# close = 0.9 * nearest bound = 0.9 / bd_factor = 1.2 and inf -> infinity (we do not keep the far bound)
LLFF_FOCUS_DEPTH = 1.2 / 0.25


def default_path(scene) -> str:
    """The run video's path: a spiral for forward-facing scenes, an orbit otherwise."""
    return "spiral" if scene.ray_space.forward_facing else "orbit"


def make_path(trainer, kind: str, frames: int, scale: float = 1.0) -> CameraPath:
    """The camera path ``kind`` (orbit | spiral | test | a .json file) with about ``frames`` frames.

    ``scale`` multiplies the training views' resolution (e.g. 0.5 for a half-size video)."""
    views = trainer.views
    h, w = max(int(round(views.height * scale)), 2), max(int(round(views.width * scale)), 2)
    sx, sy = w / views.width, h / views.height
    intr = dict(height=h, width=w, focal=views.focal * sx, cx=views.cx * sx, cy=views.cy * sy)
    if kind.endswith(".json"):
        return read_camera_path_json(kind, (h, w))
    if frames < 1:
        raise PathError(f"--frames must be >= 1, got {frames}")
    train = training_cameras(trainer)
    if kind == "orbit":
        if trainer.scene.ray_space.forward_facing:
            raise PathError("orbit needs an object-centric scene; forward-facing (LLFF) scenes: use --path spiral")
        return CameraPath(orbit_path(train, frames), **intr)
    if kind == "spiral":
        if trainer.scene.ray_space.forward_facing:
            return CameraPath(llff_spiral_path(train, frames, LLFF_FOCUS_DEPTH), **intr)
        return CameraPath(orbit_path(train, frames, elevation_swing=True), **intr)
    if kind == "test":
        test = test_cameras(trainer)
        pick = np.unique(np.linspace(0, len(test) - 1, min(frames, len(test))).round().astype(int))
        tv = trainer.scene.test
        tx, ty = w / tv.width, h / tv.height
        return CameraPath(test[torch.as_tensor(pick)], h, w, tv.focal * tx, tv.cx * tx, tv.cy * ty)
    raise PathError(f"unknown camera path '{kind}': expected orbit, spiral, test or a camera_path .json file")


# ---- rendering and writing -------------------------------------------------------------------


def check_render_memory(trainer, cams: CameraPath, depth: bool = False) -> None:
    """PathError (one line) when rendering ``cams`` (one image's working memory, every frame kept for the
    video) cannot fit the run's ``memory_budget_mb`` (:func:`warpnerf.train.memory.render_bytes`)."""
    problem = over_budget(render_bytes(cams.height, cams.width, len(cams.c2w), depth), trainer.cfg.memory_budget_mb,
                          f"rendering {len(cams.c2w)} frames of {cams.width}x{cams.height}", "--scale or --frames")
    if problem:
        raise PathError(problem)


def render_frames(trainer, cams: CameraPath, depth: bool = False, progress: bool = True,
                  desc: str = "render") -> list[np.ndarray]:
    """Render every camera of ``cams``: a list of (H, W, 3) uint8 frames, or (H, 2W, 3) with the
    depth map (near = bright, background white) beside the RGB when ``depth``. PathError first when
    they cannot fit the run's memory budget (:func:`check_render_memory`). ``progress``: a bar named
    ``desc`` over the frames."""
    check_render_memory(trainer, cams, depth)
    weights = trainer.level_weights(trainer.cfg.iters)
    out = []
    for c2w in tqdm(cams.c2w, desc=desc, disable=not progress, dynamic_ncols=True, unit="frame"):
        img = trainer.renderer.render_image(c2w.to(trainer.device), cams.height, cams.width, cams.focal, cams.cx,
                                            cams.cy, weights)
        rgb = img["rgb"].clamp(0, 1).cpu()
        if depth:
            rgb = torch.cat([rgb, depth_to_rgb(img["depth"].cpu(), img["opacity"].cpu(),
                                               disparity=trainer.scene.ray_space.is_contracted)], dim=1)
        out.append((rgb.numpy() * 255 + 0.5).astype(np.uint8))
    return out


def have_ffmpeg() -> bool:
    """True if imageio can write MP4 (``imageio-ffmpeg`` installed with its ffmpeg binary)."""
    try:
        import imageio_ffmpeg  # optional extra: warpnerf[video]

        return os.path.isfile(imageio_ffmpeg.get_ffmpeg_exe())
    except Exception:
        return False


def _pad_even(frame: np.ndarray) -> np.ndarray:
    # H.264 in yuv420p needs even sides; pad with white (the background) instead of resizing
    h, w = frame.shape[:2]
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), constant_values=255) if h % 2 or w % 2 else frame


def write_video(path: str, frames: list[np.ndarray], fps: float = 24.0) -> str:
    """Write uint8 (H, W, 3) frames to ``path``: MP4 (H.264) when ffmpeg is available, else a GIF
    with the same stem (a warning says so). ``.gif`` paths are always GIFs. Returns the path written."""
    if not frames:
        raise PathError("no frames to write")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    root, ext = os.path.splitext(path)
    if ext.lower() != ".gif":
        if have_ffmpeg():
            # macro_block_size 2: frames are already padded to even sides, so imageio must not resize them
            with imageio.get_writer(path, fps=fps, codec="libx264", quality=8, pixelformat="yuv420p",
                                    macro_block_size=2, ffmpeg_log_level="error") as wr:
                for f in frames:
                    wr.append_data(_pad_even(f))
            return path
        warnings.warn("imageio-ffmpeg is not installed (pip install 'warpnerf[video]'): writing a GIF instead of "
                      f"{path}", stacklevel=2)
        path = root + ".gif"
    imageio.mimsave(path, frames, duration=1000.0 / fps, loop=0)
    return path


def render_video(trainer, out: str, path: str = "orbit", frames: int = 60, fps: float = 24.0, depth: bool = False,
                 scale: float = 1.0, progress: bool = True, desc: str = "render") -> str:
    """Render camera path ``path`` of a trained ``trainer`` into the video ``out``; returns the file written."""
    cams = make_path(trainer, path, frames, scale)
    return write_video(out, render_frames(trainer, cams, depth, progress, desc), fps)


def render_run_video(trainer, out_dir: str, frames: int, progress: bool = True) -> str:
    """The run folder's own video: ``turntable.mp4`` (``turntable.gif`` without ffmpeg) along the
    scene's default path (orbit, or spiral for forward-facing scenes)."""
    path = default_path(trainer.scene)
    return render_video(trainer, os.path.join(out_dir, "turntable.mp4"), path, frames, fps=12.0, progress=progress,
                        desc=f"turntable video ({path})")


def read_video(path: str) -> list[np.ndarray]:
    """Decode every frame of a video or GIF: a list of (H, W, 3) uint8 arrays."""
    reader = imageio.get_reader(path)
    try:
        return [np.asarray(f)[..., :3] for f in reader]
    finally:
        reader.close()
