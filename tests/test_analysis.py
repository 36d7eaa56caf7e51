"""docs/analysis/pose_offset.py: it loads and reports the offsets metrics.json holds."""

import importlib.util
import os

import torch
from test_cameras import _ring_cameras

from warpnerf import cameras as C

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


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
