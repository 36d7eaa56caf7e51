"""Camera paths and videos: ``warpnerf render`` and the run's own turntable."""

import json
import math

import numpy as np
import pytest
import torch

from chair_run import RESOLUTION, VIDEO_FRAMES  # the session fixture chair_run is in conftest.py
from warpnerf.cli import main
from warpnerf.geometry.cameras import look_at
from warpnerf.runs.video import (CameraPath, look_target, make_path, orbit_path, read_camera_path_json, read_video,
                           scene_up, write_camera_path_json, write_video, have_ffmpeg)


def _hemisphere(n=12, r=4.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    d[:, 2] = d[:, 2].abs() + 0.3
    return look_at(torch.nn.functional.normalize(d, dim=-1) * r + torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64),
                   target=(0.2, -0.1, 0.3)).float()


def test_orbit_circles_the_up_axis_around_the_look_target():
    train = _hemisphere()
    assert torch.allclose(look_target(train), torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64), atol=1e-4)
    up = scene_up(train)
    assert up[2] > 0.8  # cameras without roll above a z-up scene
    path = orbit_path(train, 16)
    centres = path[:, :, 3].double() - torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64)
    dist = centres.norm(dim=-1)
    assert torch.allclose(dist, torch.full_like(dist, 4.0), atol=1e-3)  # mean training distance
    height = centres @ up
    assert float(height.max() - height.min()) < 1e-4  # constant elevation: a circle about up
    # every camera looks at the target: -z axis is parallel to (target - centre)
    view = -path[:, :, 2].double()
    assert torch.allclose((view * -centres / dist[:, None]).sum(-1), torch.ones(16, dtype=torch.float64), atol=1e-5)
    # one full turn, evenly spaced: consecutive azimuth steps of 2 pi / 16
    flat = centres - height[:, None] * up
    cos = (torch.nn.functional.normalize(flat[1:], dim=-1) * torch.nn.functional.normalize(flat[:-1], dim=-1)).sum(-1)
    assert torch.allclose(cos, torch.full_like(cos, math.cos(2 * math.pi / 16)), atol=1e-4)
    swing = orbit_path(train, 16, elevation_swing=True)[:, :, 3].double() @ up
    assert float(swing.max() - swing.min()) > 0.1  # the object-centric spiral changes elevation


def test_camera_path_json_round_trip(tmp_path):
    cams = CameraPath(orbit_path(_hemisphere(), 5), 30, 40, 36.0, 20.0, 15.0)
    f = tmp_path / "camera_path.json"
    write_camera_path_json(str(f), cams)
    back = read_camera_path_json(str(f), (1, 1))
    assert (back.height, back.width) == (30, 40)
    assert back.focal == pytest.approx(36.0, rel=1e-6)
    assert torch.allclose(back.c2w, cams.c2w, atol=1e-6)
    f.write_text(json.dumps({"camera_path": [{"camera_to_world": [1, 2, 3]}]}))
    with pytest.raises(ValueError, match="16 numbers"):
        read_camera_path_json(str(f), (1, 1))


@pytest.mark.parametrize("ext", [".mp4", ".gif"])
def test_write_video_decodes_back(tmp_path, ext):
    if ext == ".mp4" and not have_ffmpeg():
        pytest.skip("imageio-ffmpeg not installed")
    frames = [np.full((21, 33, 3), 40 * k, np.uint8) for k in range(5)]  # odd sides: padded, not resized
    path = write_video(str(tmp_path / f"v{ext}"), frames, fps=10)
    back = read_video(path)
    assert len(back) == 5
    assert back[0].shape[:2] == ((22, 34) if ext == ".mp4" else (21, 33))
    means = [float(f[:21, :33].mean()) for f in back]
    assert np.allclose(means, [40 * k for k in range(5)], atol=3)  # lossy H.264 on flat colours: within 3 levels


def test_run_writes_mp4_turntable_and_render_command(chair_run, tmp_path, capsys):
    run = chair_run
    turntable = run / ("turntable.mp4" if have_ffmpeg() else "turntable.gif")
    frames = read_video(str(turntable))
    assert len(frames) == VIDEO_FRAMES and frames[0].shape[:2] == (RESOLUTION, RESOLUTION)
    out = tmp_path / "orbit.mp4"
    assert main(["render", "--run", str(run), "--path", "orbit", "--frames", "6", "--depth", "--out", str(out),
                 "--save-path", str(tmp_path / "cams.json"), "--quiet"]) == 0
    written = out if have_ffmpeg() else out.with_suffix(".gif")
    frames = read_video(str(written))
    assert len(frames) == 6
    assert frames[0].shape[:2] == (RESOLUTION, 2 * RESOLUTION)  # depth beside RGB
    # N distinct frames: the orbit moves the camera, so consecutive frames differ
    diffs = [np.abs(frames[i].astype(int) - frames[i + 1].astype(int)).mean() for i in range(5)]
    assert min(diffs) > 0.5, diffs
    # the saved camera path renders the same video
    out2 = tmp_path / "again.gif"
    assert main(["render", "--run", str(run), "--path", str(tmp_path / "cams.json"), "--out", str(out2), "--quiet"]) == 0
    assert len(read_video(str(out2))) == 6
    # test cameras: each at most once (the chair has 200 test views; ask for 5)
    assert main(["render", "--run", str(run), "--path", "test", "--frames", "5", "--out", str(tmp_path / "t.gif"),
                 "--quiet"]) == 0
    assert len(read_video(str(tmp_path / "t.gif"))) == 5


def test_render_bad_path_is_one_line_error(chair_run, capsys):
    assert main(["render", "--run", str(chair_run), "--path", "helix", "--quiet"]) == 2
    assert "unknown camera path 'helix'" in capsys.readouterr().err
    assert main(["render", "--run", str(chair_run), "--path", "nope.json", "--quiet"]) == 2


def test_spiral_path_of_a_run(chair_run):
    from warpnerf.runs.folder import load_run

    trainer = load_run(str(chair_run), "cpu")
    cams = make_path(trainer, "spiral", 8, scale=0.5)
    assert len(cams) == 8 and (cams.height, cams.width) == (RESOLUTION // 2, RESOLUTION // 2)
    assert cams.focal == pytest.approx(trainer.views.focal * 0.5)


def test_render_scale_beyond_the_memory_budget_is_one_line(chair_run, capsys):
    """--scale 1000: 32000 x 32000 frames would need ~65 GB each; refused before a frame is rendered."""
    from door import one_line_error, tree

    before = tree(chair_run)
    assert main(["render", "--run", str(chair_run), "--scale", "1000", "--frames", "2", "--quiet"]) == 2
    one_line_error(capsys, "rendering 2 frames of 32000x32000", "memory_budget_mb = 4096", "lower --scale")
    assert tree(chair_run) == before
