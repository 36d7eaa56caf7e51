"""``warpnerf view``: the render function for a viewer camera, render modes and the G²fR level mask,
progressive rendering, checkpoint following, and a real headless Chromium showing the served scene,
the camera frustums and a change of render mode (CI installs chromium: see .ci/run)."""

import base64
import json
import shutil
import socket
import subprocess
import tempfile
import threading
import time
import urllib.request
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import warpnerf.outputs.viewer as viewer_mod
from warpnerf.outputs.viewer import (Progressive, RunViewer, c2w_from_viser, colourise, masked_level_weights,
                                     matrix_to_quat, quat_to_matrix, viser_from_c2w)


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


def _fov_y(tr) -> float:
    return float(2 * np.arctan(0.5 * tr.views.height / tr.views.focal))


def test_render_function_returns_the_view_of_a_camera_state(chair_run):
    from warpnerf.runs.folder import load_run

    viewer = RunViewer(str(chair_run), "cpu", preview_height=24)
    tr = viewer.trainer
    c2w = tr.train_c2w[3].cpu()
    pos, wxyz = viser_from_c2w(c2w)
    fov_y = _fov_y(tr)
    img = viewer.render_viser_camera(pos, wxyz, fov_y, aspect=1.5)
    assert img.shape == (24, 36, 3) and img.dtype == np.uint8
    assert img.std() > 5  # not a blank frame
    # the same camera through the renderer directly: identical pixels (conventions and intrinsics agree)
    focal = 0.5 * 24 / np.tan(0.5 * fov_y)
    ref = tr.renderer.render_image(c2w, 24, 36, float(focal), 18.0, 12.0, tr.level_weights(viewer.step))["rgb"]
    assert np.abs(img.astype(int) - (ref.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)).max() <= 1
    # and at the training camera's own intrinsics it matches what training saw (PSNR well above noise);
    # the viewer keeps no image, so the training image comes from load_run
    h = tr.views.height
    full = viewer.render_viser_camera(pos, wxyz, fov_y, aspect=1.0, height=h)
    mse = ((full / 255.0 - load_run(str(chair_run), "cpu").views.images[3].numpy()) ** 2).mean()
    assert -10 * np.log10(mse) > 14


def _refuse_decoding(m: pytest.MonkeyPatch) -> None:
    """Any image decoded (PIL, imageio) fails; opening one for its header does not decode it."""
    import imageio.v3 as iio
    import PIL.Image
    import PIL.ImageFile

    def refuse(*args, **kwargs):
        raise AssertionError("the viewer's start-up decoded an image")

    m.setattr(PIL.ImageFile.ImageFile, "load", refuse)
    m.setattr(PIL.Image.Image, "load", refuse)
    m.setattr(iio, "imread", refuse)


def test_the_viewer_loads_what_load_run_loads_but_keeps_no_image(chair_run, monkeypatch):
    """load_for_viewing: the same cameras, intrinsics, ray space, background and field as load_run, without
    the val split, the images (zero-stride stand-ins of the same shape, no image decoded: the scene is loaded
    cameras-only, with the background the checkpoint records) or Adam's moments."""
    from warpnerf.runs.folder import load_run

    ref = load_run(str(chair_run), "cpu")
    with monkeypatch.context() as m:
        _refuse_decoding(m)
        viewer = RunViewer(str(chair_run), "cpu", preview_height=16)
    tr = viewer.trainer
    assert tr.cameras_only and not tr.scene.pixels and ref.scene.pixels
    assert tr.scene.background_note == ref.scene.background_note
    assert (tr.scene.train.alpha is None) == (ref.scene.train.alpha is None)
    assert torch.equal(tr.train_c2w, ref.train_c2w) and torch.equal(tr.scene.test.c2w, ref.scene.test.c2w)
    for attr in ("focal", "cx", "cy", "height", "width"):
        assert getattr(tr.views, attr) == getattr(ref.views, attr)
        assert getattr(tr.scene.test, attr) == getattr(ref.scene.test, attr)
    assert tr.scene.ray_space == ref.scene.ray_space and tr.scene.background == ref.scene.background
    assert (tr.scene.name, tr.scene.source, tr.scene.root) == (ref.scene.name, ref.scene.source, ref.scene.root)
    assert viewer.step == ref.step and ref.scene.val is not None and tr.scene.val is None
    for views, full in ((tr.views, ref.views), (tr.scene.test, ref.scene.test)):
        assert views.images.shape == full.images.shape and set(views.images.stride()) == {0}
    assert tr.images.shape == ref.images.shape and set(tr.images.stride()) == {0}
    assert not tr.optimizer.state and ref.optimizer.state  # no Adam moments loaded
    weights = ref.level_weights(ref.step)
    a = tr.renderer.render_image(ref.train_c2w[2], 12, 12, 15.0, 6.0, 6.0, weights)
    b = ref.renderer.render_image(ref.train_c2w[2], 12, 12, 15.0, 6.0, 6.0, weights)
    assert torch.equal(a["rgb"], b["rgb"]) and torch.equal(a["depth"], b["depth"])


def test_the_run_records_its_background_and_older_runs_are_decoded(chair_run, tmp_path, capsys):
    """The checkpoint and metrics.json record the background training settled (warpnerf.data.background:
    detecting it needs the pixels); a run from before they did is loaded in full, and views the same."""
    from warpnerf.data.background import SettledBackground
    from warpnerf.outputs.viewer import load_for_viewing
    from warpnerf.runs.folder import load_run

    ref = load_run(str(chair_run), "cpu")
    want = SettledBackground.of(ref.scene, ref.cfg.background).to_dict()
    assert torch.load(chair_run / "checkpoint.pt")["scene_background"] == want
    assert json.loads((chair_run / "metrics.json").read_text())["scene_background"] == want
    run = tmp_path / "old"
    shutil.copytree(chair_run, run, ignore=shutil.ignore_patterns("renders", "*.mp4", "*.gif"))
    state = torch.load(run / "checkpoint.pt")
    del state["scene_background"]
    torch.save(state, run / "checkpoint.pt")
    old = load_for_viewing(str(run), "cpu")
    assert not old.cameras_only and not old.scene.pixels and old.scene.val is None
    assert "trained before checkpoints recorded the background" in capsys.readouterr().err
    assert set(old.images.stride()) == {0} and set(old.scene.test.images.stride()) == {0}
    assert old.scene.background == ref.scene.background and old.scene.ray_space == ref.scene.ray_space
    weights = ref.level_weights(ref.step)
    a = old.renderer.render_image(ref.scene.test.c2w[1], 12, 12, 15.0, 6.0, 6.0, weights)
    b = ref.renderer.render_image(ref.scene.test.c2w[1], 12, 12, 15.0, 6.0, 6.0, weights)
    assert torch.equal(a["rgb"], b["rgb"]) and torch.equal(a["depth"], b["depth"])


def test_a_run_of_the_heldout_schedule_is_viewed_with_its_val_cameras(chair_run, tmp_path, monkeypatch):
    """The held-out G²fR schedule's trainer reads the val split (Trainer refuses a scene without one): the viewer
    keeps it for such a run, cameras-only like the rest."""
    from warpnerf.cli.app import main
    from warpnerf.outputs.viewer import load_for_viewing

    run = tmp_path / "heldout"
    assert main(["train", "--scene", "chair", "--task", "full", "--builtin-resolution", "32", "--iters", "4",
                 "--eval-max-views", "1", "--video-frames", "0", "--quiet", "--config", str(chair_run.parent / "tiny.toml"),
                 "--g2fr", "--g2fr-schedule", "heldout", "--out", str(run)]) == 0
    with monkeypatch.context() as m:
        _refuse_decoding(m)
        tr = load_for_viewing(str(run), "cpu")
    assert tr.cameras_only and tr.scene.val is not None and set(tr.scene.val.images.stride()) == {0}


def test_bench_viewer_times_fresh_processes_and_records(chair_run, tmp_path, capsys):
    from warpnerf.cli.app import main

    records = tmp_path / "records"
    assert main(["bench", "viewer", "--run", str(chair_run), "--repeats", "1", "--json", "--device", "cpu",
                 "--threads", "1", "--record", "viewer_start", "--records-dir", str(records)]) == 0
    out = capsys.readouterr().out.splitlines()
    res = json.loads(out[0])
    assert res["cameras_only"] and res["scene"] == "chair" and res["repeats"] == 1 and res["threads"] == 1
    assert res["load_seconds_first"] > 0 and res["peak_rss_mb_max"] > 50 and res["image_size"] == [32, 32]
    assert len(res["load_seconds"]) == len(res["process_seconds"]) == len(res["peak_rss_mb"]) == 1
    assert out[1].startswith(f"record: {records / 'viewer_start.json'}")
    from warpnerf.runs.record import load_record

    rec = load_record(str(records / "viewer_start.json"))
    assert rec["kind"] == "bench" and rec["bench"]["what"] == "viewer" and rec["runs"] == []
    assert rec["source_run"]["metrics"]["scene"] == "chair"
    assert main(["bench", "step", "--record", "x", "--records-dir", str(records)]) == 2
    assert "bench viewer records them" in capsys.readouterr().err


def test_render_modes_level_mask_and_cancellable_bands(chair_run, monkeypatch):
    viewer = RunViewer(str(chair_run), "cpu", preview_height=24)
    tr = viewer.trainer
    c2w = tr.train_c2w[3].cpu()
    pos, wxyz = viser_from_c2w(c2w)
    fov_y = _fov_y(tr)
    focal = float(0.5 * 24 / np.tan(0.5 * fov_y))
    run_weights = tr.level_weights(viewer.step)
    out = tr.renderer.render_image(c2w, 24, 24, focal, 12.0, 12.0, run_weights)

    def view(**kw):
        return viewer.render_viser_camera(pos, wxyz, fov_y, 1.0, **kw).astype(int)

    rgb, depth, acc = view(), view(mode="depth"), view(mode="accumulation")
    assert not (rgb[..., 0] == rgb[..., 2]).all()  # the chair is coloured
    # depth: grey, as `warpnerf render --depth` draws it; near is bright, empty pixels white
    assert (depth[..., 0] == depth[..., 1]).all() and (depth[..., 1] == depth[..., 2]).all()
    assert np.abs(depth - colourise(out, "depth")).max() <= 1
    opaque = (out["opacity"] > 0.5).numpy()
    assert 0.05 < opaque.mean() < 0.95 and (depth[~opaque] == 255).all() and depth[opaque].mean() < 240
    # accumulation: the opacity, grey
    assert np.abs(acc[..., 0] - out["opacity"].numpy() * 255).max() <= 1 and (acc[..., 1] == acc[..., 0]).all()
    with pytest.raises(ValueError):
        view(mode="normals")
    # the G²fR level mask: the coarsest level only is another picture, the renderer's with the finer levels at 0
    n_levels = len(run_weights)
    assert n_levels > 1 and masked_level_weights(run_weights, n_levels) == run_weights
    one = view(levels=1)
    ref1 = tr.renderer.render_image(c2w, 24, 24, focal, 12.0, 12.0, masked_level_weights(run_weights, 1))["rgb"]
    assert np.abs(one - (ref1.clamp(0, 1).numpy() * 255 + 0.5).astype(int)).max() <= 1
    assert np.abs(one - rgb).mean() > 2
    assert np.array_equal(view(levels=n_levels), rgb)
    # full renders go in bands of rows (here 4 rows of 24): the same image, dropped when cancelled
    monkeypatch.setattr(viewer_mod, "BAND_PIXELS", 96)
    asked = []
    banded = view(cancelled=lambda: asked.append(1) and False)
    assert len(asked) == 6 and np.abs(banded - rgb).max() <= 1
    asked.clear()
    assert viewer.render_viser_camera(pos, wxyz, fov_y, 1.0, cancelled=lambda: len(asked) > 2 or asked.append(1)) is None
    assert len(asked) == 3  # three bands rendered, dropped before the fourth


def test_progressive_reduced_while_changing_full_once_still():
    now = [0.0]
    p = Progressive(idle=0.3, clock=lambda: now[0])
    assert not p.refine_due()  # no camera reported yet
    v1 = p.changed()
    assert p.plan() == (v1, False)  # just moved: reduced
    now[0] = 0.2
    v2 = p.changed()  # moved again
    now[0] = 0.45
    assert not p.refine_due()  # 0.25 s after the last move
    now[0] = 0.55
    assert p.refine_due() and not p.refine_due()  # due once
    version, full = p.plan()
    assert (version, full) == (v2, True) and not p.cancelled(version)
    assert not p.refine_due()  # its full render is under way: not a second one
    p.changed()  # a move during the full render cancels it
    assert p.cancelled(version)
    now[0] = 1.0
    assert p.refine_due()
    assert p.plan()[1]
    now[0] = 10.0
    assert not p.refine_due()  # done: nothing until the next change
    p.changed()
    assert p.plan()[1] is False


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


def _chromium_or_skip() -> None:
    pytest.importorskip("viser")
    pytest.importorskip("websockets")
    if not (shutil.which("chromium") or shutil.which("chromium-browser")):
        pytest.skip("chromium not installed (apt-get install -y chromium)")


class Chromium:
    """Headless Chromium driven over the DevTools protocol: open a page, take screenshots. The
    page is real (software WebGL), and waits are real time, not virtual time."""

    def __init__(self, size=(480, 360)):
        self.size = size

    def __enter__(self) -> "Chromium":
        from websockets.sync.client import connect

        port = _free_port()
        self.profile = tempfile.mkdtemp()
        self.proc = subprocess.Popen(
            [shutil.which("chromium") or shutil.which("chromium-browser"), "--headless", "--no-sandbox",
             "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", f"--user-data-dir={self.profile}",
             f"--window-size={self.size[0]},{self.size[1]}", f"--remote-debugging-port={port}", "about:blank"],
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
            self.ws = connect(ws_url, max_size=None)
        except BaseException:
            self._close_browser()
            raise
        self.counter = 0
        self.call("Emulation.setDeviceMetricsOverride", width=self.size[0], height=self.size[1], deviceScaleFactor=1,
                  mobile=False)
        self.call("Page.enable")
        return self

    def call(self, method, **params):
        self.counter += 1
        self.ws.send(json.dumps({"id": self.counter, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == self.counter:
                return msg.get("result", {})

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def screenshot_png(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def _close_browser(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)
        shutil.rmtree(self.profile, ignore_errors=True)

    def __exit__(self, *exc) -> None:
        try:
            self.ws.close()
        finally:
            self._close_browser()


def chromium_screenshot(url: str, size=(480, 360), ready=lambda: True, timeout: float = 90.0) -> bytes:
    """PNG of ``url`` in headless Chromium, taken once ``ready()`` is true plus 3 s."""
    with Chromium(size) as browser:
        browser.open(url)
        _wait_until(ready, timeout)
        time.sleep(3.0)  # the image travels to the page and is drawn
        return browser.screenshot_png()


def _wait_until(condition, timeout: float) -> bool:
    t_end = time.time() + timeout
    while not condition():
        if time.time() > t_end:
            return False
        time.sleep(0.2)
    return True


def _png_to_float(png: bytes, path) -> np.ndarray:
    import imageio.v2 as imageio

    path.write_bytes(png)
    return imageio.imread(path)[..., :3].astype(float) / 255


def _wait_for_server(port: int) -> None:
    for _ in range(60):
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=1)
            return
        except OSError:
            time.sleep(0.5)


def test_headless_chromium_shows_the_scene(chair_run, tmp_path):
    _chromium_or_skip()
    from warpnerf.outputs.viewer import serve

    viewer = RunViewer(str(chair_run), "cpu", preview_height=120)
    port = _free_port()
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(viewer, "127.0.0.1", port, 0.5, stop), daemon=True)
    thread.start()
    try:
        _wait_for_server(port)
        png = chromium_screenshot(f"http://127.0.0.1:{port}", ready=lambda: viewer.renders > 0)
    finally:
        stop.set()
        thread.join(30)
    shot = _png_to_float(png, tmp_path / "viewer.png")
    assert viewer.renders > 0, "the browser never reported a camera"
    assert shot.shape[:2] == (360, 480)
    # the chair (brown wood, red cushion) fills the middle of the canvas behind viser's panels;
    # an empty viser page is white/grey there. Count saturated, not-white pixels in the centre.
    centre = shot[140:300, 60:260]
    sat = centre.max(-1) - centre.min(-1)
    chair_like = (sat > 0.12) & (centre.max(-1) < 0.95)
    assert chair_like.mean() > 0.03, chair_like.mean()


def _frustum_blue(img: np.ndarray) -> np.ndarray:
    """Pixels of the training frustums' colour (40, 90, 220): clearly blue, not grey, not the chair."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (b > 0.5) & (b - r > 0.25) & (b - g > 0.15)


def test_headless_chromium_shows_frustums_progressive_frames_and_a_depth_mode(chair_run, tmp_path):
    """The served page in a real browser: the training frustums are drawn (and go when their box is
    unticked), the first image is the reduced one and the full one follows once the camera is still,
    nothing is rendered while it stays still, and choosing "depth" in the panel serves the depth map."""
    _chromium_or_skip()
    from warpnerf.outputs.viewer import MOVING_FRACTION, serve

    viewer = RunViewer(str(chair_run), "cpu", preview_height=120)
    n_train, n_test = len(viewer.trainer.train_c2w), len(viewer.trainer.scene.test.c2w)
    port, stop, apps = _free_port(), threading.Event(), []
    thread = threading.Thread(target=serve, args=(viewer, "127.0.0.1", port, 0.5, stop),
                              kwargs=dict(ready=apps.append), daemon=True)
    thread.start()
    size = (800, 600)  # the panel takes the right ~340 pixels; the scene is left of it
    try:
        _wait_for_server(port)
        assert _wait_until(lambda: apps, 30)
        app = apps[0]
        # one frustum node per camera in the scene tree; the test cameras are there but hidden at first
        assert len(app.frustums["train"]) == n_train and len(app.frustums["test"]) == n_test
        assert app.server.scene.get_handle_by_name("/cameras/train/0") is app.frustums["train"][0]
        assert all(h.visible for h in app.frustums["train"]) and not any(h.visible for h in app.frustums["test"])
        with Chromium(size) as browser:
            browser.open(f"http://127.0.0.1:{port}")
            assert _wait_until(lambda: any(f.full for f in app.frames.values()), 120), "no full frame"
            time.sleep(3.0)
            rgb_shot = _png_to_float(browser.screenshot_png(), tmp_path / "rgb.png")
            (cid, frame), = app.frames.items()
            sent = [(shape, full) for c, shape, full, mode in app.recent if c == cid]
            # quiet: nothing more is rendered while the camera does not move
            n_renders = viewer.renders
            time.sleep(2.0)
            assert viewer.renders == n_renders
            # untick the training cameras: their frustums leave the page
            app.show["train"].value = False
            assert not any(h.visible for h in app.frustums["train"])
            time.sleep(3.0)
            bare_shot = _png_to_float(browser.screenshot_png(), tmp_path / "bare.png")
            app.show["train"].value = True
            # depth, chosen in the panel's dropdown (as a click would set it)
            app.mode.value = "depth"
            assert _wait_until(lambda: app.frames[cid].mode == "depth" and app.frames[cid].full, 120)
            time.sleep(3.0)
            depth_shot = _png_to_float(browser.screenshot_png(), tmp_path / "depth.png")
            depth_frame = app.frames[cid]
            client = app.server.get_clients()[cid]
            cam = client.camera
            expected = viewer.render_viser_camera(cam.position, cam.wxyz, cam.fov, cam.aspect,
                                                  depth_frame.image.shape[0], mode="depth")
            # a click on a frustum moves the browser's camera onto that training camera
            target = app.frustums["train"][5]
            app._jump(SimpleNamespace(client=client), target, viewer.initial_fov())
            assert _wait_until(lambda: np.allclose(cam.position, target.position, atol=1e-4)
                               and abs(abs(np.dot(cam.wxyz, target.wxyz)) - 1) < 1e-6, 30)
    finally:
        stop.set()
        thread.join(30)
    # progressive: a reduced image first, then the full one (120 rows: the max height, under the window's)
    assert not sent[0][1] and sent[0][0][0] == max(8, round(120 * MOVING_FRACTION)), sent
    assert frame.full and frame.image.shape[0] == 120 and (sent[-1][1] and sent[-1][0] == frame.image.shape[:2])
    # frustums: blue lines over the scene, left of the panel (the axes gizmo at the bottom left, whose z axis
    # is blue too, left out), that go when unticked
    scene = np.zeros(rgb_shot.shape[:2], bool)
    scene[:, :450] = True
    scene[520:, :80] = False
    with_frustums, without = (_frustum_blue(rgb_shot) & scene).sum(), (_frustum_blue(bare_shot) & scene).sum()
    assert with_frustums > 200 and without < with_frustums / 10, (with_frustums, without)
    # depth: the served image is the grey depth map (exactly what the renderer's depth gives), not the RGB one
    img = depth_frame.image
    assert (img[..., 0] == img[..., 1]).all() and (img[..., 1] == img[..., 2]).all()
    assert np.abs(img.astype(int) - expected.astype(int)).max() <= 1
    assert not (frame.image[..., 0] == frame.image[..., 2]).all()  # the RGB frame is coloured
    # ... and the page shows it: the chair's colours are gone from the centre, which is now grey
    centre = (slice(200, 520), slice(60, 400))

    def coloured(shot):  # saturated, not white, not a frustum line
        c = shot[centre]
        return ((c.max(-1) - c.min(-1) > 0.12) & (c.max(-1) < 0.95) & ~_frustum_blue(c)).mean()

    assert coloured(rgb_shot) > 0.03 and coloured(depth_shot) < coloured(rgb_shot) / 4, (coloured(rgb_shot),
                                                                                         coloured(depth_shot))
    assert np.abs(depth_shot[centre] - rgb_shot[centre]).mean() > 0.02
