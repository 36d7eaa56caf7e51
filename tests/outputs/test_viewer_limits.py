"""``warpnerf view`` limits (issue #64): a browser's reported canvas cannot size a render beyond
the configured maximum, another site's page cannot connect, one render per browser at a time,
and the printed URL names the port actually served."""

import math
import socket
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from warpnerf.outputs.viewer import LatestOnly, clamp_render_size, origin_allowed, parse_size


def test_any_reported_canvas_gives_a_bounded_render_with_the_aspect_kept():
    rng = np.random.default_rng(0)
    aspects = [2000.0, 1 / 2000, 1e9, 1e-9, 1.0, 16 / 9, 0.0, -3.0, math.nan, math.inf, -math.inf]
    aspects += list(10 ** rng.uniform(-4, 4, 200))
    heights = [160, 1, 0, -5, 1e7, math.nan, math.inf, 4000, 1080, 1079.6]
    for max_w, max_h, max_px in [(1920, 1080, 1920 * 1080), (640, 480, 100_000), (1920, 1080, 256)]:
        for a in aspects:
            for h in heights:
                hh, ww = clamp_render_size(h, a, max_w, max_h, max_px)
                assert isinstance(hh, int) and isinstance(ww, int)
                assert 1 <= hh <= max_h and 1 <= ww <= max_w and (hh * ww <= max_px or min(hh, ww) == 1)
                if math.isfinite(a) and a > 0 and min(hh, ww) >= 8:  # aspect kept up to rounding
                    assert abs(ww / hh - a) / a < 0.15, (h, a, hh, ww)
    assert clamp_render_size(160, 2000.0) == (1, 1920)  # the probe's 2000x1 canvas: not 320000x160
    assert clamp_render_size(160, 1.5) == (160, 240)  # ordinary sizes untouched
    assert clamp_render_size(100_000, 16 / 9) == (1080, 1920)


def test_render_obeys_the_limit():
    from warpnerf.outputs.viewer import RunViewer

    seen = []
    viewer = RunViewer.__new__(RunViewer)
    viewer.preview_height, viewer.max_width, viewer.max_height, viewer.max_pixels = 160, 64, 48, 2000
    viewer.step, viewer.lock = 0, threading.Lock()

    def render_image(c2w, h, w, focal, cx, cy, weights):
        seen.append((h, w, focal))
        return {"rgb": torch.zeros(h, w, 3)}

    viewer.trainer = SimpleNamespace(device="cpu", level_weights=lambda step: None,
                                     renderer=SimpleNamespace(render_image=render_image))
    img = viewer.render(torch.eye(4)[:3], math.nan, aspect=2000.0)
    assert img.shape[0] * img.shape[1] <= 2000 and img.shape[1] <= 64 and math.isfinite(seen[0][2])


def test_max_size_parsing():
    assert parse_size("1920x1080") == (1920, 1080)
    for bad in ("big", "1920", "0x0", "10x10", "-5x100", "1920x1080x3"):
        with pytest.raises(ValueError):
            parse_size(bad)


def test_only_the_viewers_own_page_connects_unless_allowed():
    assert origin_allowed("http://localhost:8080", "localhost:8080")
    assert origin_allowed("http://127.0.0.1:8081/", "127.0.0.1:8081")
    assert origin_allowed(None, "localhost:8080")  # not a browser
    assert not origin_allowed("http://evil.example", "localhost:8080")
    assert not origin_allowed("http://localhost:9999", "localhost:8080")
    assert not origin_allowed("null", "localhost:8080")
    assert origin_allowed("http://evil.example", "localhost:8080", ["http://evil.example/"])
    assert origin_allowed("http://evil.example", "localhost:8080", ["*"])


def test_one_render_per_client_newer_requests_replace_older():
    queue, runs, started, release = LatestOnly(), [], threading.Event(), threading.Event()

    def slow(tag):
        def job():
            runs.append(tag)
            started.set()
            release.wait(5)
        return job

    t = threading.Thread(target=queue.submit, args=("a", slow(0)))
    t.start()
    assert started.wait(5)
    handed = [queue.submit("a", slow(i)) for i in range(1, 20)]  # while rendering: queued, newest wins
    assert not any(handed)
    assert queue.submit("b", lambda: runs.append("b"))  # another client is not blocked by a's queue
    release.set()
    t.join(5)
    assert runs == [0, "b", 19]


class _FakeViewer:
    """What serve() asks of a RunViewer, without a run."""

    run_dir, step, renders, preview_height, max_height = "run", 0, 0, 32, 1080

    def __init__(self):
        self.trainer = SimpleNamespace(cfg=SimpleNamespace(scene="fake", task="full", iters=1, g2fr=False))

    def initial_camera(self):
        return torch.eye(4)[:3] + torch.tensor([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 4.0]])

    def look_at(self):
        return np.zeros(3)

    def up_direction(self):
        return np.array([0.0, 1.0, 0.0])

    def initial_fov(self):
        return 0.8

    def camera_sets(self):
        from warpnerf.outputs.viewer import CameraSet

        return {"train": CameraSet("training cameras", self.initial_camera()[None], 0.8, 1.0, (40, 90, 220))}

    def run_level_weights(self):
        return None

    def training_state(self):
        from warpnerf.outputs.viewer import TrainingState

        return TrainingState(False, False, False, True, "finished")

    def reload_if_changed(self):
        return False

    def render_viser_camera(self, *a, **k):
        self.renders += 1
        return np.zeros((4, 4, 3), np.uint8)


def _serve_in_thread(port, **kw):
    from warpnerf.outputs.viewer import serve

    stop, got = threading.Event(), []
    ready = threading.Event()

    def announce(p):
        got.append(p)
        ready.set()

    th = threading.Thread(target=serve, args=(_FakeViewer(), "127.0.0.1", port, 0.2, stop),
                          kwargs=dict(announce=announce, **kw), daemon=True)
    th.start()
    assert ready.wait(30)
    return stop, th, got[0]


def test_the_printed_port_is_the_served_port_when_the_asked_one_is_busy(monkeypatch, capsys):
    pytest.importorskip("viser")
    import warpnerf.outputs.viewer as viewer_mod
    from warpnerf.cli import main

    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    port = busy.getsockname()[1]
    served = []
    real_serve = viewer_mod.serve

    def serve_briefly(viewer, host, port_, **kw):
        stop = threading.Event()
        announce = kw.pop("announce")

        def wrapped(p):
            served.append(p)
            announce(p)
            stop.set()

        return real_serve(viewer, host, port_, 0.05, stop, announce=wrapped, **kw)

    monkeypatch.setattr(viewer_mod, "RunViewer", lambda *a, **k: _FakeViewer())
    monkeypatch.setattr(viewer_mod, "serve", serve_briefly)
    try:
        assert main(["view", "--run", "nowhere", "--port", str(port)]) == 0
    finally:
        busy.close()
    out = capsys.readouterr().out
    line = [ln for ln in out.splitlines() if ln.startswith("warpnerf view: http")]
    assert len(line) == 1 and served and served[0] != port
    assert f":{served[0]} " in line[0] and f"port {port} was busy" in line[0]


@pytest.mark.parametrize("origin, closed", [("http://evil.example", True), (None, False), ("same", False)])
def test_a_cross_origin_websocket_is_closed(origin, closed):
    pytest.importorskip("viser")
    import viser
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    stop, th, port = _serve_in_thread(free)
    try:
        headers = {}
        if origin == "same":
            headers["Origin"] = f"http://127.0.0.1:{port}"
        elif origin:
            headers["Origin"] = origin
        ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                     additional_headers=headers, open_timeout=10, max_size=None)
        t_end, was_closed = time.time() + 4, False
        try:
            while time.time() < t_end:
                try:
                    ws.recv(timeout=0.5)
                except TimeoutError:
                    continue
                except ConnectionClosed as e:
                    was_closed = True
                    assert e.rcvd is None or e.rcvd.code == 1008
                    break
        finally:
            ws.close()
        assert was_closed == closed
    finally:
        stop.set()
        th.join(30)


def test_bad_view_flags_are_one_line_exit_2(capsys, tmp_path):
    pytest.importorskip("viser")
    from warpnerf.cli import main

    before = sorted(p.name for p in tmp_path.iterdir())
    for flags in (["--max-size", "huge"], ["--max-pixels", "0"], ["--preview-height", "0"],
                  ["--preview-height", "5000"], ["--port", "70000"]):
        assert main(["view", "--run", str(tmp_path), *flags]) == 2
        err = capsys.readouterr().err.strip()
        assert err and len(err.splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before
