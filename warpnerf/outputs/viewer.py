"""``warpnerf view``: a live viewer of a run in the browser (viser, ``pip install 'warpnerf[viewer]'``).

The viser server serves a three.js page; every time a browser's camera moves, the server
renders the field from that camera at preview resolution (``preview_height`` pixels tall, the
browser's aspect) and sends it as the page's background image. Viser cameras follow OpenCV
(x right, y down, looking down +z); warpnerf's c2w follow OpenGL (x right, y up, looking down
-z), hence the flip of the y and z axes in :func:`c2w_from_viser`.

Limits: a browser reports its own canvas size, so every render is clamped by
:func:`clamp_render_size` to ``max_width`` x ``max_height`` and ``max_pixels`` (aspect kept), each
browser has at most one render queued (a newer camera replaces an older one, :class:`LatestOnly`),
and websocket connections whose ``Origin`` is not the page's own (or one of ``allow_origins``) are
closed before anything is rendered for them (:func:`origin_allowed`).

Attaching to a training run: ``warpnerf train --checkpoint-every 100`` writes ``checkpoint.pt``
(with its step, so the G²fR level weights match) every 100 steps; the viewer polls the file's
modification time and reloads it, re-rendering every connected browser.
"""

from __future__ import annotations

import math
import os
import threading
import time
from typing import Callable, Iterable, Optional
from urllib.parse import urlsplit

import numpy as np
import torch

from warpnerf.runs.folder import CHECKPOINT, load_run, read_checkpoint
from warpnerf.runs.video import look_target
from warpnerf.train.views import test_cameras, training_cameras

_GL_FROM_CV = np.diag([1.0, -1.0, -1.0])

MAX_WIDTH, MAX_HEIGHT = 1920, 1080  # default --max-size
MAX_PIXELS = MAX_WIDTH * MAX_HEIGHT  # default pixel budget of one render


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


class RunViewer:
    """A run's field, rendered for viewer cameras; reloads the checkpoint when it changes.

    Args:
        run_dir: run folder (``config.toml`` and ``checkpoint.pt``).
        preview_height: rendered image height in pixels (width from the browser's aspect).
        max_size: (width, height) no render exceeds (:func:`clamp_render_size`).
        max_pixels: pixel budget of one render.
    """

    def __init__(self, run_dir: str, device: str = "auto", preview_height: int = 160,
                 max_size: tuple[int, int] = (MAX_WIDTH, MAX_HEIGHT), max_pixels: int = MAX_PIXELS):
        self.run_dir = run_dir
        self.ckpt = os.path.join(run_dir, CHECKPOINT)
        self.preview_height = int(preview_height)
        self.max_width, self.max_height = (int(v) for v in max_size)
        self.max_pixels = int(max_pixels)
        self.trainer = load_run(run_dir, device)
        self.lock = threading.Lock()  # one render or reload at a time
        self._mtime = os.path.getmtime(self.ckpt)
        self.step = self.trainer.step  # the checkpoint's step (load_run restored it)
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
            self.trainer.load_state_dict(state)
            self.step = self._step_of(state)
            self._mtime = mtime
        return True

    def look_at(self) -> np.ndarray:
        """(3,) the point the training cameras look at (forward-facing scenes: 1 unit ahead of the first test camera)."""
        if self.trainer.scene.ray_space.forward_facing:
            c = self.initial_camera()
            return (c[:, 3] - c[:, 2]).double().numpy()
        return look_target(training_cameras(self.trainer)).numpy()

    def initial_camera(self) -> torch.Tensor:
        """(3, 4) the first test camera (in the field's frame): where the browser starts."""
        return test_cameras(self.trainer)[0]

    @torch.no_grad()
    def render(self, c2w: torch.Tensor, fov_y: float, aspect: float, height: Optional[int] = None) -> np.ndarray:
        """(H, W, 3) uint8 render from an OpenGL (3, 4) camera with vertical field of view
        ``fov_y`` (radians) and width/height ``aspect``, clamped by :func:`clamp_render_size`."""
        h, w = clamp_render_size(height or self.preview_height, aspect, self.max_width, self.max_height,
                                 self.max_pixels)
        fov_y = float(fov_y)
        if not (math.isfinite(fov_y) and 1e-3 < fov_y < math.pi - 1e-3):
            fov_y = 1.0  # a browser's nonsense fov: ~57 degrees instead of a non-finite focal length
        focal = 0.5 * h / np.tan(0.5 * fov_y)
        with self.lock:
            weights = self.trainer.level_weights(self.step)
            img = self.trainer.renderer.render_image(c2w.to(self.trainer.device), h, w, float(focal), w / 2, h / 2,
                                                     weights)
        return (img["rgb"].clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)

    def render_viser_camera(self, position, wxyz, fov_y: float, aspect: float, height: Optional[int] = None):
        """:meth:`render` for a viser camera state (position, OpenCV wxyz, vertical fov in radians, aspect)."""
        return self.render(c2w_from_viser(position, wxyz), fov_y, aspect, height)


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


def serve(viewer: RunViewer, host: str = "127.0.0.1", port: int = 8080, poll_seconds: float = 2.0,
          stop: Optional[threading.Event] = None, allow_origins: Iterable[str] = (),
          announce: Optional[Callable[[int], None]] = None):
    """Serve ``viewer`` with viser until ``stop`` is set (or forever). Returns the server after stop.

    ``announce(port)`` is called once the server listens, with the port it actually bound (viser
    moves on to the next free port when ``port`` is busy). Browsers whose page comes from another
    origin than the viewer's own (and not in ``allow_origins``; ``*`` allows all) are disconnected
    before anything is rendered for them."""
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
    up = viewer.trainer.train_c2w[:, :, 1].mean(0).cpu().double().numpy()
    up = up / np.linalg.norm(up)
    server.scene.set_up_direction(tuple(float(v) for v in up))
    # where new browsers start (and "Reset View" returns): the first test camera, looking at the scene
    server.initial_camera.position = tuple(float(v) for v in c2w0[:, 3])
    server.initial_camera.look_at = tuple(float(v) for v in viewer.look_at())
    server.initial_camera.up = tuple(float(v) for v in up)
    server.initial_camera.fov = float(2 * np.arctan(0.5 * viewer.trainer.views.height / viewer.trainer.views.focal))
    status = server.gui.add_markdown(f"**{os.path.basename(os.path.abspath(viewer.run_dir))}** step {viewer.step}")
    queue = LatestOnly()  # one render per browser at a time; newer cameras replace queued ones

    def render_for(client) -> None:
        if stop.is_set():  # shutting down: the connection is closing
            return
        cam = client.camera
        try:
            img = viewer.render_viser_camera(cam.position, cam.wxyz, cam.fov, cam.aspect)
        except Exception as e:  # a render error must not kill the server thread
            if not stop.is_set():
                print(f"warpnerf view: render failed: {e}", flush=True)
            return
        viewer.renders += 1
        client.scene.set_background_image(img, format="jpeg", jpeg_quality=90)

    def update(client) -> None:
        queue.submit(client.client_id, lambda: render_for(client))

    @server.on_client_connect
    def _(client) -> None:
        # the browser reports its camera (initial pose, then every move): render for each report
        @client.camera.on_update
        def _(_cam) -> None:
            update(client)

    while not stop.wait(poll_seconds):
        if viewer.reload_if_changed():
            status.content = f"**{os.path.basename(os.path.abspath(viewer.run_dir))}** step {viewer.step} (reloaded)"
            for client in server.get_clients().values():
                update(client)
    server.stop()
    return server


def wait_for_checkpoint(run_dir: str, timeout: float) -> bool:
    """Wait until ``run_dir/checkpoint.pt`` exists (a training run that has not saved yet)."""
    t_end = time.time() + timeout
    while not os.path.exists(os.path.join(run_dir, "checkpoint.pt")):
        if time.time() > t_end:
            return False
        time.sleep(1.0)
    return True
