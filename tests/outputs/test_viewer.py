"""``warpnerf view``: the render function for a viewer camera, checkpoint following, and a real
headless Chromium showing the served scene (CI installs chromium: see .ci/run)."""

import base64
import json
import shutil
import socket
import subprocess
import tempfile
import threading
import time
import urllib.request

import numpy as np
import pytest
import torch

from warpnerf.outputs.viewer import RunViewer, c2w_from_viser, matrix_to_quat, quat_to_matrix, viser_from_c2w


def test_quaternion_and_camera_conventions_round_trip():
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        q = torch.nn.functional.normalize(torch.randn(4, generator=g, dtype=torch.float64), dim=0).numpy()
        r = quat_to_matrix(q)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
        q2 = matrix_to_quat(r)
        assert np.allclose(q2 * np.sign(q2[0]), q * np.sign(q[0]), atol=1e-9)
    c2w = torch.tensor([[1.0, 0, 0, 0.5], [0, 0, -1, -4], [0, 1, 0, 0.3]])  # OpenGL camera looking along +y
    pos, wxyz = viser_from_c2w(c2w)
    # viser/OpenCV: +z is the viewing direction, +y points down
    r = quat_to_matrix(wxyz)
    assert np.allclose(r[:, 2], [0, 1, 0], atol=1e-6) and np.allclose(r[:, 1], [0, 0, -1], atol=1e-6)
    assert torch.allclose(c2w_from_viser(pos, wxyz), c2w, atol=1e-6)


def test_render_function_returns_the_view_of_a_camera_state(chair_run):
    viewer = RunViewer(str(chair_run), "cpu", preview_height=24)
    tr = viewer.trainer
    c2w = tr.train_c2w[3].cpu()
    pos, wxyz = viser_from_c2w(c2w)
    fov_y = float(2 * np.arctan(0.5 * tr.views.height / tr.views.focal))
    img = viewer.render_viser_camera(pos, wxyz, fov_y, aspect=1.5)
    assert img.shape == (24, 36, 3) and img.dtype == np.uint8
    assert img.std() > 5  # not a blank frame
    # the same camera through the renderer directly: identical pixels (conventions and intrinsics agree)
    focal = 0.5 * 24 / np.tan(0.5 * fov_y)
    ref = tr.renderer.render_image(c2w, 24, 36, float(focal), 18.0, 12.0, tr.level_weights(viewer.step))["rgb"]
    assert np.abs(img.astype(int) - (ref.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)).max() <= 1
    # and at the training camera's own intrinsics it matches what training saw (PSNR well above noise)
    h = tr.views.height
    full = viewer.render_viser_camera(pos, wxyz, fov_y, aspect=1.0, height=h)
    mse = ((full / 255.0 - tr.views.images[3].numpy()) ** 2).mean()
    assert -10 * np.log10(mse) > 14


def test_viewer_follows_a_training_checkpoint(chair_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(chair_run, run, ignore=shutil.ignore_patterns("renders", "*.mp4", "*.gif"))
    viewer = RunViewer(str(run), "cpu", preview_height=16)
    assert not viewer.reload_if_changed()
    state = torch.load(run / "checkpoint.pt")
    state["step"] = 7
    with torch.no_grad():
        state["field"] = {k: torch.zeros_like(v) if k.startswith("encoder") else v for k, v in state["field"].items()}
    time.sleep(0.05)
    torch.save(state, run / "checkpoint.pt")
    assert viewer.reload_if_changed()
    assert viewer.step == 7 and float(viewer.trainer.field.encoder.state_dict()[next(iter(
        viewer.trainer.field.encoder.state_dict()))].abs().sum()) == 0.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def chromium_screenshot(url: str, size=(480, 360), ready=lambda: True, timeout: float = 90.0) -> bytes:
    """PNG of ``url`` in headless Chromium, taken once ``ready()`` is true plus 3 s (the page
    is driven over the DevTools protocol, so the wait is real time, not virtual time)."""
    from websockets.sync.client import connect

    port = _free_port()
    profile = tempfile.mkdtemp()
    proc = subprocess.Popen(
        [shutil.which("chromium") or shutil.which("chromium-browser"), "--headless", "--no-sandbox", "--disable-gpu",
         "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
         f"--remote-debugging-port={port}", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        t_end = time.time() + 30
        while True:
            try:
                targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=1))
                break
            except OSError:
                if time.time() > t_end:
                    raise
                time.sleep(0.3)
        ws_url = next(t["webSocketDebuggerUrl"] for t in targets if t["type"] == "page")
        with connect(ws_url, max_size=None) as ws:
            counter = [0]

            def call(method, **params):
                counter[0] += 1
                ws.send(json.dumps({"id": counter[0], "method": method, "params": params}))
                while True:
                    msg = json.loads(ws.recv(timeout=60))
                    if msg.get("id") == counter[0]:
                        return msg.get("result", {})

            call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1, mobile=False)
            call("Page.enable")
            call("Page.navigate", url=url)
            t_end = time.time() + timeout
            while not ready() and time.time() < t_end:
                time.sleep(0.5)
            time.sleep(3.0)  # the image travels to the page and is drawn
            return base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
    finally:
        proc.terminate()
        proc.wait(10)


def test_headless_chromium_shows_the_scene(chair_run, tmp_path):
    pytest.importorskip("viser")
    pytest.importorskip("websockets")
    if not (shutil.which("chromium") or shutil.which("chromium-browser")):
        pytest.skip("chromium not installed (apt-get install -y chromium)")
    import imageio.v2 as imageio

    from warpnerf.outputs.viewer import serve

    viewer = RunViewer(str(chair_run), "cpu", preview_height=120)
    port = _free_port()
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(viewer, "127.0.0.1", port, 0.5, stop), daemon=True)
    thread.start()
    try:
        for _ in range(60):
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=1)
                break
            except OSError:
                time.sleep(0.5)
        png = chromium_screenshot(f"http://127.0.0.1:{port}", ready=lambda: viewer.renders > 0)
    finally:
        stop.set()
        thread.join(30)
    (tmp_path / "viewer.png").write_bytes(png)
    shot = imageio.imread(tmp_path / "viewer.png")[..., :3].astype(float) / 255
    assert viewer.renders > 0, "the browser never reported a camera"
    assert shot.shape[:2] == (360, 480)
    # the chair (brown wood, red cushion) fills the middle of the canvas behind viser's panels;
    # an empty viser page is white/grey there. Count saturated, not-white pixels in the centre.
    centre = shot[140:300, 60:260]
    sat = centre.max(-1) - centre.min(-1)
    chair_like = (sat > 0.12) & (centre.max(-1) < 0.95)
    assert chair_like.mean() > 0.03, chair_like.mean()
