"""``warpnerf view``: a live viewer of a run in the browser (viser, ``pip install 'warpnerf[viewer]'``).

The viser server serves a three.js page; whenever a browser's camera moves, the server renders the
field from that camera and sends it as the page's background image. Viser cameras follow OpenCV
(x right, y down, looking down +z); warpnerf's c2w follow OpenGL (x right, y up, looking down -z),
hence the flip of the y and z axes in :func:`c2w_from_viser`.

Progressive rendering (:class:`Progressive`): while a view changes (camera, panel, checkpoint) it is
rendered at :data:`MOVING_FRACTION` of its full height; once it has not changed for
:data:`IDLE_SECONDS` it is rendered again at full height: the browser window's height, at most the
panel's "max height" (``--preview-height``). A full render goes in bands of rows and is dropped
between bands as soon as the view changes again.

The panel: the run's step and training state (Pause / Resume of a live training through
``RUN/PAUSE``, :mod:`warpnerf.train.pause`), render mode (RGB, depth, accumulation), max height,
the G²fR levels (how many of the run's active levels to render with) and the camera frustums
(training and test cameras; for the pose task also the initial noisy poses and the true ones,
aligned into the field's frame). Clicking a frustum moves the browser's camera there.

Limits: a browser reports its own canvas size, so every render is clamped by
:func:`clamp_render_size` to ``max_width`` x ``max_height`` and ``max_pixels`` (aspect kept), each
browser has at most one render queued (a newer camera replaces an older one, :class:`LatestOnly`),
and websocket connections whose ``Origin`` is not the page's own (or one of ``allow_origins``) are
closed before anything is rendered for them (:func:`origin_allowed`).

Attaching to a training run: ``warpnerf train --checkpoint-every 100`` writes ``checkpoint.pt``
(with its step, so the G²fR level weights match) every 100 steps; the viewer polls the file's
modification time and reloads it, re-rendering every connected browser.

Start-up: the viewer renders and never trains, so :func:`load_for_viewing` reads no val split, no
optimizer state and no pixel: the scene is loaded cameras-only (poses, intrinsics, image sizes from the
file headers, normalisation and ray space as training had them; the images are zero-stride stand-ins)
with the background the run's checkpoint records, since the detection of a background needs the pixels.
Runs from before checkpoints recorded it are loaded in full and their images dropped afterwards.
"""

from __future__ import annotations

import ctypes
import gc
import math
import os
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Iterable, Optional
from urllib.parse import urlsplit

import numpy as np
import torch

from warpnerf.data.scene import stand_in_like
from warpnerf.geometry.cameras import map_gt_poses_to_estimate_frame
from warpnerf.model.g2fr import LevelWeights
from warpnerf.runs.folder import (CHECKPOINT, CONFIG, METRICS, RunLock, load_run, load_state_checked,
                                  read_checkpoint, read_run_config)
from warpnerf.runs.video import look_target
from warpnerf.train.config import ConfigError
from warpnerf.train.evaluate import depth_to_rgb
from warpnerf.train.pause import pause_path
from warpnerf.train.trainer import Trainer
from warpnerf.train.views import test_cameras, training_cameras

_GL_FROM_CV = np.diag([1.0, -1.0, -1.0])

MAX_WIDTH, MAX_HEIGHT = 1920, 1080  # default --max-size
MAX_PIXELS = MAX_WIDTH * MAX_HEIGHT  # default pixel budget of one render
CPU_PREVIEW_HEIGHT = 160  # default max height on a CPU (~40k pixels: about a second); on a GPU: the window's
MODES = ("RGB", "depth", "accumulation")
MOVING_FRACTION = 0.25  # height of the renders while a view changes, relative to the full one
MIN_MOVING_HEIGHT = 8
IDLE_SECONDS = 0.3  # a view unchanged this long is rendered at full height
BAND_PIXELS = 1 << 14  # a full render goes in bands of about this many pixels, dropped when the view changes
SHOWN_CAMERAS = ("train", "initial", "true")  # frustums drawn at first; test cameras (often hundreds) when asked


def clamp_render_size(height: float, aspect: float, max_width: int = MAX_WIDTH, max_height: int = MAX_HEIGHT,
                      max_pixels: int = MAX_PIXELS) -> tuple[int, int]:
    """(height, width) of a render ``height`` pixels tall with width/height ``aspect``, scaled down
    (aspect kept) to fit ``max_width`` x ``max_height`` and ``max_pixels``; at least 1 x 1.

    The aspect comes from the browser's canvas, so anything is possible: a non-finite or
    non-positive aspect or height falls back to 1.0 / 1 pixel.

    >>> clamp_render_size(160, 2000.0)  # a 2000x1 canvas: 1920 wide, not 320000
    (1, 1920)
    >>> clamp_render_size(160, 1.5)
    (160, 240)
    """
    aspect = float(aspect) if isinstance(aspect, (int, float)) and math.isfinite(aspect) and aspect > 0 else 1.0
    h = float(height) if isinstance(height, (int, float)) and math.isfinite(height) and height >= 1 else 1.0
    w = h * aspect
    scale = min(1.0, max_width / w, max_height / h, math.sqrt(max_pixels / (w * h)))
    h, w = h * scale, w * scale
    hi, wi = max(int(round(h)), 1), max(int(round(w)), 1)
    # rounding up may step over a limit by a pixel: floor then
    if wi > max_width or hi > max_height or wi * hi > max_pixels:
        hi, wi = max(int(h), 1), max(int(w), 1)
    return min(hi, max_height), min(wi, max_width)


def parse_size(text: str) -> tuple[int, int]:
    """``"1920x1080"`` -> (1920, 1080); ValueError for anything else (or a side < 16)."""
    parts = str(text).lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise ValueError(f"--max-size {text!r}: expected WIDTHxHEIGHT, e.g. 1920x1080")
    w, h = int(parts[0]), int(parts[1])
    if w < 16 or h < 16:
        raise ValueError(f"--max-size {text!r}: width and height must be >= 16")
    return w, h


def origin_allowed(origin: Optional[str], host_header: Optional[str], allow_origins: Iterable[str] = ()) -> bool:
    """Whether a websocket handshake's ``Origin`` may connect: the page's own origin (its
    host:port equals the ``Host`` the browser connected to), one listed in ``allow_origins``, or
    ``*`` there. No ``Origin`` (not a browser: scripts, curl) is allowed; a browser always sends one,
    so another site's page cannot drive the viewer through the visitor's browser."""
    allow = {a.rstrip("/").lower() for a in allow_origins}
    if "*" in allow or origin is None:
        return True
    origin = origin.strip().rstrip("/").lower()
    if origin in allow:
        return True
    if not host_header:
        return False
    try:
        netloc = urlsplit(origin).netloc
    except ValueError:
        return False
    return bool(netloc) and netloc == host_header.strip().lower()


class LatestOnly:
    """At most one job per key running, newer requests replacing queued ones.

    :meth:`submit` runs ``job`` now if nothing runs for ``key``; otherwise it marks the key dirty
    and returns at once, and the running call runs ``job`` once more when it finishes (the job
    reads the newest state itself, e.g. the browser's current camera). N camera updates during
    one slow render cost two renders, not N."""

    def __init__(self):
        self._lock = threading.Lock()
        self._busy: set = set()
        self._again: dict = {}

    def submit(self, key, job: Callable[[], None]) -> bool:
        """True if this call ran the job (perhaps several times), False if it was handed over."""
        with self._lock:
            if key in self._busy:
                self._again[key] = job
                return False
            self._busy.add(key)
        try:
            while True:
                job()
                with self._lock:
                    job = self._again.pop(key, None)
                    if job is None:
                        self._busy.discard(key)
                        return True
        except BaseException:
            with self._lock:
                self._busy.discard(key)
                self._again.pop(key, None)
            raise


def quat_to_matrix(wxyz) -> np.ndarray:
    """(3, 3) rotation of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in wxyz)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a (3, 3) rotation (Shepperd's method, numerically safe branch)."""
    m = np.asarray(r, np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def c2w_from_viser(position, wxyz) -> torch.Tensor:
    """(3, 4) OpenGL camera-to-world from a viser camera (position (3,), OpenCV rotation wxyz)."""
    r = quat_to_matrix(wxyz) @ _GL_FROM_CV
    return torch.as_tensor(np.concatenate([r, np.asarray(position, np.float64)[:, None]], 1), dtype=torch.float32)


def viser_from_c2w(c2w: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), wxyz (4,)) of a (3, 4) OpenGL camera-to-world."""
    m = c2w.detach().cpu().double().numpy()
    return m[:, 3].copy(), matrix_to_quat(m[:, :3] @ _GL_FROM_CV)


def colourise(out: dict, mode: str = "RGB", disparity: bool = False) -> np.ndarray:
    """(H, W, 3) uint8 picture of a render (``rgb``, ``depth``, ``opacity``) in ``mode``:
    RGB; depth as :func:`~warpnerf.train.evaluate.depth_to_rgb` draws it (grey, near = bright,
    empty pixels white; ``disparity`` for contracted scenes); accumulation: opacity, black = empty."""
    if mode == "depth":
        img = depth_to_rgb(out["depth"].float().cpu(), out["opacity"].float().cpu(), disparity=disparity)
    elif mode == "accumulation":
        o = out["opacity"].float().cpu().clamp(0, 1)
        img = o[..., None].expand(*o.shape, 3)
    elif mode == "RGB":
        img = out["rgb"].float().cpu().clamp(0, 1)
    else:
        raise ValueError(f"unknown render mode {mode!r}: expected one of {', '.join(MODES)}")
    return (img.numpy() * 255 + 0.5).astype(np.uint8)


def masked_level_weights(weights: Optional[LevelWeights], levels: Optional[int]) -> Optional[LevelWeights]:
    """``weights`` with every level from ``levels`` on (0-based, coarse first) set to 0: the field
    rendered with its ``levels`` coarsest levels only (G²fR's mask, applied at render time).

    >>> masked_level_weights(LevelWeights((1.0, 1.0, 0.5, 0.0)), 2).values
    (1.0, 1.0, 0.0, 0.0)
    """
    if weights is None or levels is None:
        return weights
    return LevelWeights(tuple(w if m < int(levels) else 0.0 for m, w in enumerate(weights.values)))


def _release_memory() -> None:
    gc.collect()
    try:  # glibc keeps freed heap pages unless asked to return them
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


def load_for_viewing(run_dir: str, device: str = "auto", progress: bool = False) -> Trainer:
    """:func:`~warpnerf.runs.folder.load_run` for a viewer, which renders and never trains: the same
    scene (same checks) but without its val split (kept, without pixels, for a run of the held-out G²fR
    schedule, whose trainer reads it), its pixels or the optimizer's moments. The scene is
    loaded cameras-only (``load_run(..., pixels=False)``): image sizes from the file headers, no image
    decoded, zero-stride stand-ins of the images' shapes, the background the checkpoint records. The
    training and test cameras, intrinsics, ray space and background are those ``load_run`` gives.

    A run whose checkpoint predates the recorded background is loaded in full (its images decoded, so
    its background is detected as in training; one line on stderr says so), then its images, the
    error map and the optimizer's moments are dropped (their memory given back). ``trainer.cameras_only``
    says which it was."""
    for p in (os.path.join(run_dir, CONFIG), os.path.join(run_dir, CHECKPOINT)):
        if not os.path.exists(p):
            raise ConfigError(f"not a run folder with a checkpoint: {p} is missing")
    cfg = read_run_config(run_dir)
    # the held-out G2fR schedule's trainer reads val views (cameras-only, they cost nothing)
    val = ("val",) if cfg.g2fr and cfg.g2fr_schedule == "heldout" else ()
    trainer = load_run(run_dir, device, progress, splits=("train", *val, "test"), optimizer=False, pixels=False)
    trainer.error_map = None
    trainer.cameras_only = not trainer.scene.pixels  # for the start-up benchmark (warpnerf.outputs.viewer_bench)
    if trainer.scene.pixels:  # an older run: loaded in full, its pixels dropped now
        print(f"warpnerf: note: {run_dir} was trained before checkpoints recorded the background: its images were "
              "decoded to detect it as training did", file=sys.stderr)
        trainer.scene.drop_pixels()
        trainer.views.drop_pixels()  # the task's own Views for a subset of the training views
        trainer.images, trainer.alpha = stand_in_like(trainer.images), stand_in_like(trainer.alpha)
        _release_memory()
    return trainer


class Progressive:
    """When one browser's view is rendered at full height.

    Every change (:meth:`changed`: the camera moved, a panel setting, a new checkpoint) bumps
    :attr:`version`; :meth:`plan` says whether the render to make now is full (nothing changed for
    ``idle`` seconds) or reduced; :meth:`refine_due` is true once per still period, unless a full
    render of that version was already planned. A full render is cancelled (:meth:`cancelled`) when
    the version moves on (its still period then ends, and the next one gets its own)."""

    def __init__(self, idle: float = IDLE_SECONDS, clock: Callable[[], float] = time.monotonic):
        self.idle, self.clock = float(idle), clock
        self._lock = threading.Lock()
        self.version = 0
        self._changed_at = -math.inf
        self._full_version = -1  # version of the last full render planned (made, running or failed: not retried)
        self._scheduled = False  # a refine was handed out and has not been planned yet

    def changed(self) -> int:
        with self._lock:
            self.version += 1
            self._changed_at = self.clock()
            return self.version

    def plan(self) -> tuple[int, bool]:
        """(version, full) of the render to make now."""
        with self._lock:
            self._scheduled = False
            full = self.clock() - self._changed_at >= self.idle
            if full:
                self._full_version = self.version
            return self.version, full

    def refine_due(self) -> bool:
        """True (once) when the view has been still for ``idle`` seconds and no full render of it was planned."""
        with self._lock:
            due = (self.version > 0 and not self._scheduled and self._full_version != self.version
                   and self.clock() - self._changed_at >= self.idle)
            if due:
                self._scheduled = True
            return due

    def cancelled(self, version: int) -> bool:
        return self.version != version


@dataclass
class CameraSet:
    """Cameras the viewer draws as frustums."""

    label: str
    c2w: torch.Tensor  # (N, 3, 4) OpenGL, in the field's frame
    fov_y: float  # radians
    aspect: float  # width / height
    color: tuple[int, int, int]


@dataclass
class TrainingState:
    """Whether a training process writes into the run folder, and whether it is paused."""

    live: bool  # a live process holds the run's lock
    pause_file: bool  # RUN/PAUSE exists
    paused: bool  # ... and the training saved its checkpoint after it appeared (it waits)
    finished: bool  # metrics.json: the run is complete
    text: str  # one line for the panel


class RunViewer:
    """A run's field, rendered for viewer cameras; reloads the checkpoint when it changes.

    Args:
        run_dir: run folder (``config.toml`` and ``checkpoint.pt``).
        preview_height: full render height in pixels (width from the browser's aspect); the panel's
            max height starts here. None: the window's height on a GPU, :data:`CPU_PREVIEW_HEIGHT` on a CPU.
        max_size: (width, height) no render exceeds (:func:`clamp_render_size`).
        max_pixels: pixel budget of one render.
    """

    def __init__(self, run_dir: str, device: str = "auto", preview_height: Optional[int] = None,
                 max_size: tuple[int, int] = (MAX_WIDTH, MAX_HEIGHT), max_pixels: int = MAX_PIXELS):
        self.run_dir = run_dir
        self.ckpt = os.path.join(run_dir, CHECKPOINT)
        self.max_width, self.max_height = (int(v) for v in max_size)
        self.max_pixels = int(max_pixels)
        self.trainer = load_for_viewing(run_dir, device)
        if preview_height is None:
            preview_height = self.max_height if self.trainer.device.type == "cuda" else CPU_PREVIEW_HEIGHT
        self.preview_height = min(int(preview_height), self.max_height)
        self.lock = threading.Lock()  # one render band or reload at a time
        self._mtime = os.path.getmtime(self.ckpt)
        self.step = self.trainer.step  # the checkpoint's step (restored with it)
        self.renders = 0  # images sent to browsers (tests read it)

    def _step_of(self, state: dict) -> int:
        return int(state.get("step", self.trainer.cfg.iters))

    def reload_if_changed(self) -> bool:
        """Reload ``checkpoint.pt`` if its modification time changed; True if it did."""
        try:
            mtime = os.path.getmtime(self.ckpt)
        except OSError:
            return False
        if mtime == self._mtime:
            return False
        try:
            state = read_checkpoint(self.run_dir, map_location=self.trainer.device)
        except Exception:  # caught mid-write by a training process (or not a checkpoint): try again at the next poll
            return False
        with self.lock:
            load_state_checked(self.trainer, state, self.run_dir, optimizer=False)
            self.step = self._step_of(state)
            self._mtime = mtime
        return True

    # --- cameras ------------------------------------------------------------------------------

    def look_at(self) -> np.ndarray:
        """(3,) the point the training cameras look at (forward-facing scenes: 1 unit ahead of the first test camera)."""
        if self.trainer.scene.ray_space.forward_facing:
            c = self.initial_camera()
            return (c[:, 3] - c[:, 2]).double().numpy()
        return look_target(training_cameras(self.trainer)).numpy()

    def initial_camera(self) -> torch.Tensor:
        """(3, 4) the first test camera (in the field's frame): where the browser starts."""
        return test_cameras(self.trainer)[0]

    def up_direction(self) -> np.ndarray:
        """(3,) unit mean of the training cameras' up vectors."""
        up = self.trainer.train_c2w[:, :, 1].mean(0).cpu().double().numpy()
        return up / np.linalg.norm(up)

    def initial_fov(self) -> float:
        """Vertical field of view (radians) of the training views."""
        return float(2 * np.arctan(0.5 * self.trainer.views.height / self.trainer.views.focal))

    def camera_sets(self) -> dict[str, CameraSet]:
        """The cameras to draw, by key: ``train`` and ``test`` in the field's frame; for the pose task
        ``train`` is the estimated poses, ``initial`` the noisy ones training started from and
        ``true`` the ground truth mapped into the field's frame by the estimate's Sim(3) alignment."""
        tr = self.trainer
        views, test = tr.views, tr.scene.test
        fov = self.initial_fov()
        sets = {"train": CameraSet("training cameras", training_cameras(tr), fov, views.width / views.height,
                                   (40, 90, 220)),
                "test": CameraSet("test cameras", test_cameras(tr),
                                  float(2 * np.arctan(0.5 * test.height / test.focal)), test.width / test.height,
                                  (150, 60, 190))}
        task = tr.task
        if hasattr(task, "noisy_c2w") and hasattr(task, "gt_c2w"):
            sets["train"].label = "training cameras (estimated)"
            with torch.no_grad():
                sim3 = task.evaluate()["sim3"]
                true = map_gt_poses_to_estimate_frame(task.gt_c2w.double(), sim3).float().cpu()
            sets["initial"] = CameraSet("initial poses (noisy)", task.noisy_c2w.detach().float().cpu(), fov,
                                        sets["train"].aspect, (235, 120, 30))
            sets["true"] = CameraSet("true poses (aligned)", true, fov, sets["train"].aspect, (40, 170, 70))
        return sets

    # --- G²fR levels ----------------------------------------------------------------------------

    def run_level_weights(self) -> Optional[LevelWeights]:
        """The G²fR level weights of the checkpoint's step (all ones without G²fR)."""
        return self.trainer.level_weights(self.step)

    def level_weights(self, levels: Optional[int] = None) -> Optional[LevelWeights]:
        """:meth:`run_level_weights`, only the ``levels`` coarsest kept (:func:`masked_level_weights`)."""
        return masked_level_weights(self.run_level_weights(), levels)

    # --- rendering -----------------------------------------------------------------------------

    @torch.no_grad()
    def render(self, c2w: torch.Tensor, fov_y: float, aspect: float, height: Optional[int] = None,
               mode: str = "RGB", levels: Optional[int] = None,
               cancelled: Optional[Callable[[], bool]] = None) -> Optional[np.ndarray]:
        """(H, W, 3) uint8 render in ``mode`` (:data:`MODES`) from an OpenGL (3, 4) camera with vertical
        field of view ``fov_y`` (radians) and width/height ``aspect``, clamped by :func:`clamp_render_size`,
        with the ``levels`` coarsest G²fR levels (None: the run's). With ``cancelled`` it renders in
        bands of rows and returns None as soon as ``cancelled()`` is true."""
        if mode not in MODES:
            raise ValueError(f"unknown render mode {mode!r}: expected one of {', '.join(MODES)}")
        h, w = clamp_render_size(height or self.preview_height, aspect, self.max_width, self.max_height,
                                 self.max_pixels)
        fov_y = float(fov_y)
        if not (math.isfinite(fov_y) and 1e-3 < fov_y < math.pi - 1e-3):
            fov_y = 1.0  # a browser's nonsense fov: ~57 degrees instead of a non-finite focal length
        focal = float(0.5 * h / np.tan(0.5 * fov_y))
        c2w = c2w.to(self.trainer.device)
        rows = h if cancelled is None else max(1, BAND_PIXELS // w)
        parts = []
        for r0 in range(0, h, rows):
            if cancelled is not None and cancelled():
                return None
            with self.lock:
                weights = self.level_weights(levels)
                # rows r0.. of the image: the same camera with its principal point moved up by r0
                parts.append(self.trainer.renderer.render_image(c2w, min(rows, h - r0), w, focal, w / 2, h / 2 - r0,
                                                                weights))
        out = {k: torch.cat([p[k] for p in parts]) for k in ("rgb", "depth", "opacity") if k in parts[0]}
        disparity = mode == "depth" and self.trainer.scene.ray_space.is_contracted
        return colourise(out, mode, disparity)

    def render_viser_camera(self, position, wxyz, fov_y: float, aspect: float, height: Optional[int] = None,
                            **kw) -> Optional[np.ndarray]:
        """:meth:`render` for a viser camera state (position, OpenCV wxyz, vertical fov in radians, aspect)."""
        return self.render(c2w_from_viser(position, wxyz), fov_y, aspect, height, **kw)

    # --- the training process -------------------------------------------------------------------

    def training_state(self) -> TrainingState:
        """Whether a live training writes this run, and whether ``RUN/PAUSE`` holds it."""
        pause = pause_path(self.run_dir)
        live = RunLock.live_owner(self.run_dir) is not None
        finished = os.path.isfile(os.path.join(self.run_dir, METRICS))
        try:
            pause_mtime = os.path.getmtime(pause)
        except OSError:
            pause_mtime = None
        paused = live and pause_mtime is not None and self._mtime >= pause_mtime
        if pause_mtime is not None and not live:
            text = f"not training; {pause} exists, so a resumed run would pause at once"
        elif paused:
            text = f"paused at step {self.step}"
        elif pause_mtime is not None:
            text = "pausing after the current step..."
        elif live:
            text = "training"
        else:
            text = "finished" if finished else f"not training (stopped at step {self.step})"
        return TrainingState(live, pause_mtime is not None, paused, finished, text)

    def set_paused(self, paused: bool) -> None:
        """Create (pause) or remove (resume) ``RUN/PAUSE``; the training polls it after every step."""
        path = pause_path(self.run_dir)
        if paused:
            with open(path, "w") as fh:
                fh.write("remove this file (or press Resume in warpnerf view) to continue training\n")
        else:
            try:
                os.unlink(path)
            except FileNotFoundError:
                pass


def _guard_origins(server, allow_origins: tuple) -> bool:
    """Close websocket connections whose Origin :func:`origin_allowed` refuses, as they open
    (before viser registers the client or anything is rendered for it). viser has no public hook
    for the handshake: this puts a connect callback first on its websocket server (viser 1.x,
    ``_websock_server``). False when this viser does not have one (connections go unchecked)."""
    ws = getattr(server, "_websock_server", None)
    callbacks = getattr(ws, "_client_connect_cb", None)
    live = getattr(ws, "_live_connections", None)
    if not isinstance(callbacks, list) or not isinstance(live, dict):
        return False

    async def check(conn) -> None:
        connection = live.get(conn.client_id)
        request = getattr(connection, "request", None)
        if request is None:
            return
        origin, host = request.headers.get("Origin"), request.headers.get("Host")
        if not origin_allowed(origin, host, allow_origins):
            print(f"warpnerf view: refused a connection from origin {origin} "
                  "(not this viewer's page; see --allow-origin)", flush=True)
            await connection.close(1008, "origin not allowed")

    callbacks.insert(0, check)
    return True


def view_url(host: str, port: int) -> str:
    return f"http://{'localhost' if host in ('127.0.0.1', '0.0.0.0', '::', '') else host}:{port}"


@dataclass
class Frame:
    """The last image sent to one browser."""

    image: np.ndarray
    full: bool  # the full-height render (else a reduced one, while the view changed)
    mode: str
    levels: int
    seconds: float


def _frustum_scale(sets: dict, look_at: np.ndarray) -> float:
    centres = np.concatenate([s.c2w[:, :, 3].double().numpy() for s in sets.values()])
    dist = np.linalg.norm(centres - look_at[None], axis=1)
    return float(max(np.median(dist), 1e-3) * 0.04)


class ViewerApp:
    """The served viewer: its panel, the frustums and each browser's progressive rendering.

    Created by :func:`serve`; its GUI handles (``mode``, ``max_height``, ``levels``, ``pause``,
    ``show``) and ``frustums`` are the viser handles, so code (and tests) can drive it as a user would.
    ``frames[client_id]`` is the last :class:`Frame` sent to each browser, ``recent`` the last ones sent."""

    def __init__(self, viewer: RunViewer, server, stop: threading.Event):
        self.viewer, self.server, self.stop = viewer, server, stop
        self.queue = LatestOnly()  # one render per browser at a time; newer requests replace queued ones
        self.states: dict[int, Progressive] = {}
        self.frames: dict[int, Frame] = {}
        self.recent: deque = deque(maxlen=64)  # (client id, (H, W), full, mode) of the last images sent, oldest first
        self._lock = threading.Lock()
        self._build_panel()
        self._add_cameras()

    # --- panel ----------------------------------------------------------------------------------

    def _build_panel(self) -> None:
        v, gui = self.viewer, self.server.gui
        self.status = gui.add_markdown(self._status_text())
        self.pause = gui.add_button("Pause training", hint="creates RUN/PAUSE: the training waits after its current "
                                                           "step (checkpoint saved) until Resume removes it")
        self.pause.on_click(lambda _event: self._toggle_pause())
        with gui.add_folder("Render"):
            self.mode = gui.add_dropdown("mode", MODES, initial_value="RGB")
            self.max_height = gui.add_slider("max height", 16, max(v.max_height, 17), 1,
                                             max(16, min(v.preview_height, v.max_height)),
                                             hint="full render height in pixels (the window's, if smaller); "
                                                  f"while the view moves: {MOVING_FRACTION:g} of it")
            self.frame_text = gui.add_markdown("no frame yet")
        weights = v.run_level_weights()
        n_levels = len(weights) if weights is not None else 0
        with gui.add_folder("G²fR levels"):
            self.level_text = gui.add_markdown(self._level_text())
            self.levels = (gui.add_slider("levels", 1, n_levels, 1, n_levels,
                                          hint="render with the coarsest levels only (finer ones masked)")
                           if n_levels > 1 else None)
        self.show: dict = {}
        with gui.add_folder("Cameras"):
            for key, cams in v.camera_sets().items():
                self.show[key] = gui.add_checkbox(cams.label, key in SHOWN_CAMERAS)
        for handle in (self.mode, self.max_height, *([self.levels] if self.levels is not None else [])):
            handle.on_update(lambda _event: self.kick_all())
        for key, box in self.show.items():
            box.on_update(lambda _event, key=key: self._show(key))
        self._refresh_training()

    def _status_text(self) -> str:
        v = self.viewer
        cfg = v.trainer.cfg
        return (f"**{os.path.basename(os.path.abspath(v.run_dir))}**: {cfg.scene}, task {cfg.task}, "
                f"step {v.step} of {cfg.iters}")

    def _level_text(self) -> str:
        weights = self.viewer.run_level_weights()
        if weights is None:
            return "no level weights"
        shown = " ".join("1" if w == 1 else "0" if w == 0 else f"{w:.2f}".lstrip("0") for w in weights)
        g2fr = "G²fR" if self.viewer.trainer.cfg.g2fr else "G²fR off"
        return f"{len(weights.active)} of {len(weights)} levels active at step {self.viewer.step} ({g2fr}): {shown}"

    def _refresh_training(self) -> None:
        state = self.viewer.training_state()
        self.training = state
        self.status.content = self._status_text() + f"  \ntraining: {state.text}"
        self.pause.label = "Resume training" if state.pause_file else "Pause training"
        self.pause.disabled = not (state.live or state.pause_file)

    def _toggle_pause(self) -> None:
        self.viewer.set_paused(not self.viewer.training_state().pause_file)
        self._refresh_training()

    # --- frustums ---------------------------------------------------------------------------------

    def _add_cameras(self) -> None:
        sets = self.viewer.camera_sets()
        self.scale = _frustum_scale(sets, self.viewer.look_at())
        self.frustums: dict[str, list] = {}
        for key, cams in sets.items():
            handles = []
            for i, c2w in enumerate(cams.c2w):
                pos, wxyz = viser_from_c2w(c2w)
                h = self.server.scene.add_camera_frustum(
                    f"/cameras/{key}/{i}", fov=cams.fov_y, aspect=cams.aspect, scale=self.scale,
                    thickness=1.5, thickness_units="screen", color=cams.color, wxyz=tuple(wxyz), position=tuple(pos),
                    visible=key in SHOWN_CAMERAS)
                h.on_click(lambda event, h=h, fov=cams.fov_y: self._jump(event, h, fov))
                handles.append(h)
            self.frustums[key] = handles
        if "initial" in sets:  # initial -> estimated centre of each training camera
            self._drift = self.server.scene.add_line_segments(
                "/cameras/initial/drift", self._drift_points(sets), (235, 120, 30), thickness=1.0,
                thickness_units="screen")

    @staticmethod
    def _drift_points(sets: dict) -> np.ndarray:
        return np.stack([sets["initial"].c2w[:, :, 3].numpy(), sets["train"].c2w[:, :, 3].numpy()], 1)

    def _update_cameras(self) -> None:
        """Move the frustums whose poses changed with a new checkpoint (pose task)."""
        sets = self.viewer.camera_sets()
        if "initial" not in sets:
            return
        for key in ("train", "true", "test"):
            for h, c2w in zip(self.frustums.get(key, []), sets[key].c2w):
                pos, wxyz = viser_from_c2w(c2w)
                h.position, h.wxyz = tuple(pos), tuple(wxyz)
        self._drift.points = self._drift_points(sets)

    def _show(self, key: str) -> None:
        visible = bool(self.show[key].value)
        for h in self.frustums.get(key, []):
            h.visible = visible
        if key == "initial" and hasattr(self, "_drift"):
            self._drift.visible = visible

    @staticmethod
    def _jump(event, frustum, fov: float) -> None:
        client = getattr(event, "client", None)
        if client is None:
            return
        with client.atomic():
            client.camera.fov = fov
            client.camera.wxyz = frustum.wxyz
            client.camera.position = frustum.position

    # --- rendering --------------------------------------------------------------------------------

    def state(self, client_id: int) -> Progressive:
        with self._lock:
            return self.states.setdefault(client_id, Progressive())

    def connect(self, client) -> None:
        state = self.state(client.client_id)

        # the browser reports its camera (initial pose, then every move and resize): render for each report
        @client.camera.on_update
        def _(_cam) -> None:
            state.changed()
            self.queue.submit(client.client_id, lambda: self.render_for(client))

    def disconnect(self, client) -> None:
        with self._lock:
            self.states.pop(client.client_id, None)
            self.frames.pop(client.client_id, None)

    def _submit_in_thread(self, client) -> None:
        threading.Thread(target=self.queue.submit, args=(client.client_id, lambda: self.render_for(client)),
                         daemon=True).start()

    def kick_all(self) -> None:
        """The view changed for every browser (panel, checkpoint): render again, reduced first."""
        for client in list(self.server.get_clients().values()):
            state = self.states.get(client.client_id)
            if state is not None and state.version > 0:  # it has reported a camera
                state.changed()
                self._submit_in_thread(client)

    def tick(self) -> None:
        """Start the full render of every browser whose view has been still long enough."""
        for client in list(self.server.get_clients().values()):
            state = self.states.get(client.client_id)
            if state is not None and state.refine_due():
                self._submit_in_thread(client)

    def full_height(self, client) -> int:
        height = int(self.max_height.value)
        window = getattr(client.camera, "image_height", None)
        if isinstance(window, int) and window > 0:
            height = min(height, window)
        return max(height, 1)

    def render_for(self, client) -> None:
        state = self.states.get(client.client_id)
        if self.stop.is_set() or state is None:  # shutting down, or the browser has gone
            return
        version, full = state.plan()
        cam = client.camera
        height = self.full_height(client)
        if not full:
            height = max(MIN_MOVING_HEIGHT, int(round(height * MOVING_FRACTION)))
        mode = self.mode.value
        levels = int(self.levels.value) if self.levels is not None else None
        t0 = time.perf_counter()
        try:
            img = self.viewer.render_viser_camera(
                cam.position, cam.wxyz, cam.fov, cam.aspect, height, mode=mode, levels=levels,
                cancelled=(lambda: state.cancelled(version) or self.stop.is_set()) if full else None)
        except Exception as e:  # a render error must not kill the server thread (a full one is not retried)
            if not self.stop.is_set():
                print(f"warpnerf view: render failed: {e}", flush=True)
            return
        if img is None:  # the view changed during a full render
            return
        seconds = time.perf_counter() - t0
        self.viewer.renders += 1
        client.scene.set_background_image(img, format="jpeg", jpeg_quality=90)
        with self._lock:
            if client.client_id in self.states:
                self.frames[client.client_id] = Frame(img, full, mode, levels or 0, seconds)
                self.recent.append((client.client_id, img.shape[:2], full, mode))
        self.frame_text.content = (f"last frame: {img.shape[1]}x{img.shape[0]} {mode}"
                                   f"{'' if full else ' (moving: reduced)'}, {seconds:.2f} s")

    def poll(self) -> None:
        """Reload a changed checkpoint (re-render every browser) and refresh the training state."""
        if self.viewer.reload_if_changed():
            self.level_text.content = self._level_text()
            self._update_cameras()
            self.kick_all()
        self._refresh_training()


def serve(viewer: RunViewer, host: str = "127.0.0.1", port: int = 8080, poll_seconds: float = 2.0,
          stop: Optional[threading.Event] = None, allow_origins: Iterable[str] = (),
          announce: Optional[Callable[[int], None]] = None, ready: Optional[Callable[[ViewerApp], None]] = None,
          tick_seconds: float = 0.05):
    """Serve ``viewer`` with viser until ``stop`` is set (or forever). Returns the server after stop.

    ``announce(port)`` is called once the server listens, with the port it actually bound (viser
    moves on to the next free port when ``port`` is busy); ``ready(app)`` once the panel and the
    frustums exist (:class:`ViewerApp`). Browsers whose page comes from another origin than the
    viewer's own (and not in ``allow_origins``; ``*`` allows all) are disconnected before anything
    is rendered for them."""
    try:
        import viser  # optional extra: warpnerf[viewer]
    except ImportError:
        raise RuntimeError("warpnerf view needs viser: pip install 'warpnerf[viewer]'") from None

    stop = stop or threading.Event()
    allow_origins = tuple(allow_origins)
    server = viser.ViserServer(host=host, port=port, verbose=False)
    if "*" not in allow_origins and not _guard_origins(server, allow_origins):
        print("warpnerf view: this viser version does not expose the websocket Origin; connections are not "
              "checked (keep --host 127.0.0.1)", flush=True)
    if announce is not None:
        announce(server.get_port())
    c2w0 = viewer.initial_camera()
    up = viewer.up_direction()
    server.scene.set_up_direction(tuple(float(v) for v in up))
    # where new browsers start (and "Reset View" returns): the first test camera, looking at the scene
    server.initial_camera.position = tuple(float(v) for v in c2w0[:, 3])
    server.initial_camera.look_at = tuple(float(v) for v in viewer.look_at())
    server.initial_camera.up = tuple(float(v) for v in up)
    server.initial_camera.fov = viewer.initial_fov()
    app = ViewerApp(viewer, server, stop)
    server.on_client_connect(app.connect)
    server.on_client_disconnect(app.disconnect)
    if ready is not None:
        ready(app)
    next_poll = time.monotonic() + poll_seconds
    while not stop.wait(tick_seconds):
        app.tick()
        if time.monotonic() >= next_poll:
            next_poll = time.monotonic() + poll_seconds
            app.poll()
    server.stop()
    return server


def wait_for_checkpoint(run_dir: str, timeout: float) -> bool:
    """Wait until ``run_dir/checkpoint.pt`` exists (a training run that has not saved yet)."""
    t_end = time.time() + timeout
    while not os.path.exists(os.path.join(run_dir, CHECKPOINT)):
        if time.time() > t_end:
            return False
        time.sleep(1.0)
    return True
