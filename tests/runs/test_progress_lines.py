"""What a practitioner sees: no silent phase after the training bar, the banner names what follows (#65)."""

from chair_run import TINY_TOML
from warpnerf.cli import main

# every post-training phase a pose run has, shown by its bar (stderr) when progress is on
PHASE_BARS = ("held-out check (val), step 10", "held-out check (val), step 20", "refine 2 test poses",
              "evaluate test views", "turntable video (orbit)")
LEGEND = ("progress bar: lv = active G2fR levels, occ = occupied fraction of the occupancy grid, spr = samples per ray, "
          "rays = rays per step, rot / trans = training-pose rotation error (deg) / translation error (x100)")
BANNER = ("after training: evaluation on 2 test views (--eval-max-views N renders fewer), their poses refined first "
          "(5 steps); a 3-frame turntable video (--video-frames 0 skips it)")


def _pose_run(tmp_path, monkeypatch, capsys, *extra):
    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    (tmp_path / "tiny.toml").write_text(TINY_TOML)
    code = main(["train", "--scene", "chair", "--task", "pose", "--builtin-resolution", "24", "--iters", "20",
                 "--eval-max-views", "2", "--video-frames", "3", "--pose-refine-steps", "5", "--heldout-every", "10",
                 "--checkpoint-every", "0", "--out", str(tmp_path / "run"), "--config", str(tmp_path / "tiny.toml"),
                 *extra])
    assert code == 0
    return capsys.readouterr()


def test_every_post_training_phase_shows_progress(tmp_path, monkeypatch, capsys):
    out = _pose_run(tmp_path, monkeypatch, capsys)
    lines = out.out.splitlines()
    assert lines[1] == BANNER  # right under the banner, before training starts
    assert lines.count(LEGEND) == 1  # once, not per step
    for bar in PHASE_BARS:
        assert bar in out.err, bar
    # in the order they run: the training bar, then each phase after it
    order = [out.err.rfind("train chair/pose"), out.err.rfind("held-out check (val), step 20"),
             out.err.find("refine 2 test poses"), out.err.find("evaluate test views"),
             out.err.find("turntable video (orbit)")]
    assert order[1:] == sorted(order[1:]) and order[2] > out.err.find("train chair/pose: 100%")


def test_quiet_run_shows_no_bars_and_no_legend(tmp_path, monkeypatch, capsys):
    out = _pose_run(tmp_path, monkeypatch, capsys, "--quiet")
    assert BANNER in out.out.splitlines()  # the banner is not progress: it stays
    assert "progress bar:" not in out.out
    for bar in ("train chair/pose", *PHASE_BARS):
        assert bar not in out.err, bar


def test_banner_without_video_says_so():
    from warpnerf.runs.run import after_training_line
    from warpnerf.train.config import build_config

    cfg = build_config("full", overrides={"video_frames": 0})
    assert after_training_line(cfg, 25) == ("after training: evaluation on 25 test views (--eval-max-views N renders "
                                            "fewer); no video (--video-frames 0)")
