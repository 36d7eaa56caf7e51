"""docs/analysis/pose_offset.py: it loads and reports the offsets metrics.json holds."""

import importlib.util
import os

import pytest
import torch
from test_cameras import _ring_cameras

from warpnerf.geometry import cameras as C

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _load():
    spec = importlib.util.spec_from_file_location("pose_offset", os.path.join(ROOT, "docs", "analysis", "pose_offset.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_pose_offset_reports_the_offset_metrics_json_holds(capsys):
    po = _load()
    gt = _ring_cameras(16, dtype=torch.float64)
    est = C.perturb_poses(gt, 0.01, 0.01, torch.Generator().manual_seed(3))
    po.report("end", est, gt)
    printed = capsys.readouterr().out
    expected = C.evaluate_poses(est, gt)["trans_offset_cam_x100"]
    assert "shared t (" + ", ".join(f"{x:+.4f}" for x in expected) + ")" in printed


def test_pose_offset_fits_t_y_against_the_camera_elevation(capsys):
    """A camera-frame t_y offset of a cos(elevation) + b, planted in the estimate, is what the fit prints.
    Planted by pitching each camera about its own centre, so the centres (and the Sim(3) fitted to
    them) do not move: t_w2c = (0, 0, -d) turns into (0, -d sin(theta), -d cos(theta))."""
    po = _load()
    gt = _ring_cameras(16, dtype=torch.float64)
    c = gt[:, :, 3]
    d = c.norm(dim=1)
    cos_el = torch.cos(torch.asin(c[:, 2] / d))
    assert cos_el.std() > 0.05  # the rig spans elevations
    dy = 0.01 * (-0.3 * cos_el + 0.07)  # x100 below: -0.3 cos(elevation) + 0.07
    theta = -torch.asin(dy / d)
    one, zero = torch.ones_like(theta), torch.zeros_like(theta)
    pitch = torch.stack([torch.stack([one, zero, zero], -1),
                         torch.stack([zero, theta.cos(), -theta.sin()], -1),
                         torch.stack([zero, theta.sin(), theta.cos()], -1)], -2)
    est = torch.cat([gt[:, :, :3] @ pitch, c[:, :, None]], 2)
    po.report("end", est, gt)
    printed = capsys.readouterr().out
    a, _, b = printed.split("t_y ~ ")[1].split()[:3]
    assert float(a) == pytest.approx(-0.3, abs=2e-4) and float(b) == pytest.approx(0.07, abs=2e-4)
