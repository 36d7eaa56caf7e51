"""The reproduction table: the paper's numbers (Tab. 1, Tab. 3), layout, paper numbers beside ours."""

import pytest

from warpnerf.studies.paper import BARF, MIPNERF360, NERF_SYNTHETIC, PAPER, barf_numbers, paper_numbers
from warpnerf.studies.tables import format_table


def arms(source="dataset", model="ngp"):
    w = {"psnr": 30.03, "ssim": 0.946, "lpips": 0.05, "rot_err_deg": 0.0697, "trans_err_x100": 0.497,
         "scene_source": source, "model": model}
    wo = {"psnr": 25.0, "ssim": 0.9, "lpips": 0.1, "rot_err_deg": 1.5, "trans_err_x100": 9.0, "scene_source": source,
          "model": model}
    return {"w/": w, "w/o": wo}


# (scene, task, model, arm, metric, value) read off the paper's tables
SPOT_CHECKS = [
    ("lego", "pose", "ngp", "w/", (0.049, 0.167, 32.53)), ("lego", "pose", "ngp", "w/o", (1.181, 4.361, 31.33)),
    ("mic", "pose", "ngp", "w/", (0.042, 0.139, 33.30)), ("mic", "pose", "ngp", "w/o", (0.965, 2.627, 30.02)),
    ("mic", "pose", "mtrf", "w/", (0.043, 0.164, 33.10)), ("mic", "pose", "mtrf", "w/o", (0.556, 2.104, 32.83)),
    ("lego", "pose", "mtrf", "w/", (0.051, 0.178, 28.72)), ("lego", "pose", "mtrf", "w/o", (0.354, 0.933, 27.54)),
    # first and last rows of Tab. 1 and a MipNeRF-360 row (most likely to be garbled in extraction)
    ("chair", "pose", "ngp", "w/", (0.101, 0.514, 33.98)), ("ship", "pose", "mtrf", "w/o", (0.540, 0.562, 27.69)),
    ("room", "pose", "mtrf", "w/o", (0.091, 0.132, 27.03)), ("counter", "pose", "ngp", "w/o", (0.529, 0.483, 20.96)),
]


@pytest.mark.parametrize("scene,task,model,arm,values", SPOT_CHECKS)
def test_paper_tab1_cells(scene, task, model, arm, values):
    got = paper_numbers(scene, task, model)[arm]
    assert (got["rot_err_deg"], got["trans_err_x100"], got["psnr"]) == pytest.approx(values, abs=1e-9)


def test_paper_tab3_and_barf_cells():
    assert paper_numbers("lego", "fewshot")["w/"]["psnr"] == 22.46 and paper_numbers("lego", "fewshot")["w/o"]["psnr"] == 19.85
    assert paper_numbers("mic", "fewshot")["w/"]["psnr"] == 29.92 and paper_numbers("mic", "fewshot")["w/o"]["psnr"] == 26.88
    assert paper_numbers("ship", "fewshot")["w/o"] == {"psnr": 16.23, "ssim": 0.663, "lpips": 0.306}
    assert paper_numbers("room", "fewshot")["w/"] == {"psnr": 25.14, "ssim": 0.805, "lpips": 0.186}
    assert paper_numbers("Bicycle", "fewshot")["w/o"]["psnr"] == 21.08  # case-insensitive scene names
    assert barf_numbers("lego", "pose") == {"rot_err_deg": 0.074, "trans_err_x100": 0.430, "psnr": 28.03}
    assert barf_numbers("counter", "pose")["rot_err_deg"] == 26.91 and barf_numbers("lego", "fewshot") == {}
    assert paper_numbers("lego", "fewshot", "mtrf") == {}  # Tab. 3 is NGP only


def test_paper_tables_are_complete():
    scenes = NERF_SYNTHETIC + MIPNERF360
    assert len(scenes) == 14 and set(BARF) == set(scenes)
    for scene in scenes:
        for model in ("ngp", "mtrf"):
            assert set(PAPER[(scene, "pose", model)]) == {"w/", "w/o"}
        assert set(PAPER[(scene, "fewshot", "ngp")]["w/"]) == {"psnr", "ssim", "lpips"}
    assert len(PAPER) == 14 * 3


def test_pose_table_has_paper_numbers_for_the_model():
    text = format_table("pose", {"lego": arms()}, "ngp")
    header, rule, row = text.splitlines()
    assert header.count("|") == rule.count("|") == row.count("|") == 9  # scene + 3 metrics x 2 arms + BARF
    assert "0.070 (0.049)" in row and "1.500 (1.181)" in row and "30.03 (32.53)" in row
    assert "0.497 (0.167)" in row and "BARF" in header and row.rstrip(" |").endswith("0.074 / 0.430 / 28.03")
    mtrf = format_table("pose", {"lego": arms(model="mtrf")}, "mtrf").splitlines()[2]
    assert "0.070 (0.051)" in mtrf and "27.54" in mtrf


def test_builtin_scene_gets_no_paper_numbers():
    row = format_table("fewshot", {"chair": arms(source="builtin")}).splitlines()[2]
    assert "(" not in row and "30.03" in row  # the built-in chair is not NeRF-synthetic's chair
    row = format_table("fewshot", {"chair": arms()}).splitlines()[2]
    assert "30.03 (25.72)" in row and "0.050 (0.076)" in row


def test_missing_values_are_marked():
    row = format_table("fewshot", {"lego": {"w/": {"psnr": 25.0}}}).splitlines()[2]
    assert "n/a" in row


def test_lego_mic_tables_for_both_models_and_tasks():
    """What `warpnerf table --scenes lego,mic --models ngp,mtrf --tasks pose,fewshot` prints, from given metrics."""
    from warpnerf.studies.sweep import RunResult, SweepSpec, expand
    from warpnerf.studies.tables import tables_markdown

    spec = SweepSpec(scenes=["lego", "mic"], models=["ngp", "mtrf"], tasks=["pose", "fewshot"], out="o")
    results = []
    for run in expand(spec):
        m = arms(model=run.model)["w/" if run.arm == "g2fr" else "w/o"]
        results.append(RunResult(run, status="done", metrics={**m, "iters": 20, "device": "cpu", "threads": 2},
                                 machine="box (4 CPU cores)"))
    text = tables_markdown(results)
    heads = [line for line in text.splitlines() if line.startswith("### ")]
    assert heads == ["### Camera-pose optimisation (cf. paper Tab. 1), ngp", "### Camera-pose optimisation (cf. paper Tab. 1), mtrf",
                     "### Few-shot reconstruction (cf. paper Tab. 3), ngp", "### Few-shot reconstruction (cf. paper Tab. 3), mtrf"]
    assert "ran on cpu, 2 Warp threads on box (4 CPU cores)" in text and "2-core" not in text
    assert "BARF's quantity" in text
    rows = [line for line in text.splitlines() if line.startswith("| mic |")]
    assert "0.070 (0.042)" in rows[0] and "0.070 (0.043)" in rows[1]  # Tab. 1 mic, NGP then Mtrf
    assert "30.03 (29.92)" in rows[2] and "(" not in rows[3]  # Tab. 3 is NGP only


def test_seeds_are_averaged():
    from warpnerf.studies.tables import _mean_over_seeds

    m = _mean_over_seeds([{"psnr": 20.0, "scene": "a", "g2fr": True}, {"psnr": 22.0, "scene": "a", "g2fr": True}])
    assert m == {"psnr": 21.0, "scene": "a", "g2fr": True}


def test_fewshot_heldout_gap_and_plot(tmp_path):
    """The few-shot section names the step where w/ G2fR leads the baseline most, from both arms'
    held-out PSNR histories, and the comparison plot is written."""
    from warpnerf.studies.tables import heldout_gap, plot_heldout_comparison

    arms_ = {"w/": {"heldout_history": [[499, 20.0], [999, 22.5], [1499, 23.0]]},
             "w/o": {"heldout_history": [[499, 20.5], [999, 21.0], [1499, 22.9]]}}
    step, gap, w, wo = heldout_gap(arms_)
    assert step == 999 and abs(gap - 1.5) < 1e-12 and (w, wo) == (22.5, 21.0)
    assert heldout_gap({"w/": {}, "w/o": {}}) is None
    path = tmp_path / "h.png"
    assert plot_heldout_comparison(str(path), "lego", arms_) and path.stat().st_size > 1000
    assert not plot_heldout_comparison(str(tmp_path / "none.png"), "lego", {"w/": {}})


def test_several_seeds_give_means_and_the_per_seed_gap():
    """`warpnerf table --seed 0,1,2`: cells are means over seeds and each scene's paired PSNR gaps
    (w/ - w/o per seed) are listed with their mean and spread."""
    import statistics

    from warpnerf.cli.app import build_parser
    from warpnerf.studies.sweep import RunResult, expand
    from warpnerf.studies.table import table_spec
    from warpnerf.studies.tables import tables_markdown

    psnr = {("g2fr", 0): 23.69, ("nog2fr", 0): 24.02, ("g2fr", 1): 24.00, ("nog2fr", 1): 23.98,
            ("g2fr", 2): 23.86, ("nog2fr", 2): 24.26}
    spec = table_spec(["lego"], ["fewshot"], seed=[0, 1, 2], out="o")
    assert spec.seeds == [0, 1, 2]
    results = [RunResult(run, status="done", metrics={"psnr": psnr[(run.arm, run.seed)], "ssim": 0.9, "iters": 1000})
               for run in expand(spec)]
    text = tables_markdown(results)
    assert "seeds 0, 1, 2 (mean)" in text
    gaps = [-0.33, 0.02, -0.40]
    assert "lego: PSNR w/ - w/o per seed -0.33 (seed 0), +0.02 (seed 1), -0.40 (seed 2)" in text
    assert f"mean {statistics.mean(gaps):+.2f}, std {statistics.stdev(gaps):.2f}" in text
    row = next(line for line in text.splitlines() if line.startswith("| lego |"))
    assert f"{(23.69 + 24.00 + 23.86) / 3:.2f} (22.46)" in row and f"{(24.02 + 23.98 + 24.26) / 3:.2f} (19.85)" in row

    # one seed: no per-seed sentence; the flag takes one seed or a list, and rejects repeats
    one = [r for r in results if r.run.seed == 0]
    assert "per seed" not in tables_markdown(one)
    parser = build_parser()
    assert parser.parse_args(["table", "--seed", "0,1,2"]).seed == [0, 1, 2]
    assert parser.parse_args(["table"]).seed == [0]
    with pytest.raises(SystemExit):
        parser.parse_args(["table", "--seed", "1,1"])


def test_pose_table_names_unconverged_views_under_the_table():
    rows = arms()
    rows["w/"].update(unconverged_views=[79], rot_err_deg_median=0.091, trans_err_x100_median=0.612)
    lines = format_table("pose", {"mic": rows}, "ngp").splitlines()
    assert lines[-1] == ("mic w/ G2fR: 1 view(s) not converged (79; rot. err > 1 deg and 5x the median); "
                         "median rot. err 0.091 deg, trans. err 0.612")
    assert not any("w/o G2fR" in line for line in lines)  # only arms with stuck views get a line


def test_pose_table_says_when_rotations_were_aligned_by_orientations():
    rows = arms()
    for m in rows.values():
        m["pose_alignment"] = "orientations"  # what PoseTask.metrics records on a forward-facing scene
    lines = format_table("pose", {"fern": rows}, "ngp").splitlines()
    assert lines[-1].startswith("fern: forward-facing, so the alignment's rotation is fitted to the cameras' orientations")
    centres = arms()
    for m in centres.values():
        m["pose_alignment"] = "centres"
    assert not any("orientations" in line for line in format_table("pose", {"lego": centres}, "ngp").splitlines())
