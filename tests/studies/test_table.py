"""The reproduction table: the paper's numbers (Tab. 1, Tab. 3), layout, paper numbers beside ours."""

import pytest
from chair_run import TINY_FIELD_TOML

from warpnerf.studies.paper import BARF, MIPNERF360, NERF_SYNTHETIC, PAPER, barf_numbers, paper_numbers
from warpnerf.studies.tables import format_table


def arms(source="dataset", model="ngp"):
    w = {"psnr": 30.03, "ssim": 0.946, "lpips": 0.05, "rot_err_deg": 0.0697, "rot_err_deg_barf": 0.0701,
         "trans_err_x100": 0.497,
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
    assert header.count("|") == rule.count("|") == row.count("|") == 11  # scene + 4 metrics x 2 arms + BARF
    cells = [c.strip() for c in row.strip("| ").split("|")]
    # our unclamped rotation error has no paper figure beside it; the paper's (BARF's float32 metric)
    # sits beside ours in that metric, n/a where a run predates it
    assert cells[1:5] == ["0.070", "1.500", "0.070 (0.049)", "n/a (1.181)"]
    assert "30.03 (32.53)" in row and "0.497 (0.167)" in row and "BARF" in header
    assert row.rstrip(" |").endswith("0.074 / 0.430 / 28.03")
    mtrf = format_table("pose", {"lego": arms(model="mtrf")}, "mtrf").splitlines()[2]
    assert "0.070 (0.051)" in mtrf and "27.54" in mtrf


def test_builtin_scene_gets_no_paper_numbers():
    row = format_table("fewshot", {"chair": arms(source="builtin")}).splitlines()[2]
    cells = [c.strip() for c in row.strip("| ").split("|")]
    # the built-in chair is not NeRF-synthetic's chair: named so, and no bracketed paper numbers
    assert cells == ["chair (built-in procedural, not NeRF-synthetic chair)", "30.03", "25.00", "0.946", "0.900",
                     "0.050", "0.100"]
    row = format_table("fewshot", {"chair": arms()}).splitlines()[2]
    assert row.startswith("| chair |") and "30.03 (25.72)" in row and "0.050 (0.076)" in row
    assert format_table("pose", {"lamp": arms(source="builtin")}).splitlines()[2].startswith(
        "| lamp (built-in procedural) |")


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
    assert "30.03 (29.92)" in rows[2] and "| mic | fps |" in rows[3]
    assert not any("(" in cell for cell in _cells(rows[3])[:-1])  # Tab. 3 is NGP only (the last cell: the gap, 1/1)


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
    """`warpnerf table --tasks pose --seed 0,1,2`: cells are means over seeds and each scene's paired PSNR
    gaps (w/ - w/o per seed) are listed with their mean and spread."""
    import statistics

    from warpnerf.cli.app import build_parser
    from warpnerf.studies.sweep import RunResult, expand
    from warpnerf.studies.table import table_spec
    from warpnerf.studies.tables import tables_markdown

    psnr = {("g2fr", 0): 23.69, ("nog2fr", 0): 24.02, ("g2fr", 1): 24.00, ("nog2fr", 1): 23.98,
            ("g2fr", 2): 23.86, ("nog2fr", 2): 24.26}
    spec = table_spec(["lego"], ["pose"], seed=[0, 1, 2], out="o")
    assert spec.seeds == [0, 1, 2]
    results = [RunResult(run, status="done", metrics={"psnr": psnr[(run.arm, run.seed)], "rot_err_deg": 0.1,
                                                      "trans_err_x100": 0.5, "iters": 1000})
               for run in expand(spec)]
    text = tables_markdown(results)
    assert "seeds 0, 1, 2 (mean)" in text
    gaps = [-0.33, 0.02, -0.40]
    assert "lego: PSNR w/ - w/o per seed -0.33 (seed 0), +0.02 (seed 1), -0.40 (seed 2)" in text
    assert f"mean {statistics.mean(gaps):+.2f}, std {statistics.stdev(gaps):.2f}" in text
    row = next(line for line in text.splitlines() if line.startswith("| lego |"))
    assert f"{(23.69 + 24.00 + 23.86) / 3:.2f} (32.53)" in row and f"{(24.02 + 23.98 + 24.26) / 3:.2f} (31.33)" in row

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


# ----------------------------------------------------------------------------- few-shot: seeds x view sets x arms

def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _fewshot_results(psnr, source="dataset", scene="lego", arms_=("g2fr", "adaptive", "nog2fr"), fail=()):
    """RunResults of `warpnerf table --tasks fewshot --seed 0,1,2 --view-sets fps,random --arms ...`, with
    ``psnr[(view set, arm, seed)]`` and SSIM/LPIPS derived from it; runs named in ``fail`` failed."""
    from warpnerf.studies.sweep import RunResult, expand
    from warpnerf.studies.table import table_spec

    spec = table_spec([scene], ["fewshot"], seed=[0, 1, 2], out="o", view_sets=["fps", "random"], arms=list(arms_))
    results = []
    for run in expand(spec):
        if run.name in fail:
            results.append(RunResult(run, status="failed", error="TrainingError: boom"))
            continue
        p = psnr[(run.view_set, run.arm, run.seed)]
        results.append(RunResult(run, status="done", metrics={
            "psnr": p, "ssim": p / 30, "lpips": 1 / p, "iters": 1000, "scene_source": source,
            "device": "cpu", "threads": 1}, machine="box (2 CPU cores)"))
    return results


PSNR = {("fps", "g2fr", 0): 23.69, ("fps", "adaptive", 0): 24.30, ("fps", "nog2fr", 0): 24.02,
        ("fps", "g2fr", 1): 24.00, ("fps", "adaptive", 1): 24.10, ("fps", "nog2fr", 1): 23.98,
        ("fps", "g2fr", 2): 23.86, ("fps", "adaptive", 2): 24.50, ("fps", "nog2fr", 2): 24.26,
        ("random", "g2fr", 0): 21.10, ("random", "adaptive", 0): 21.00, ("random", "nog2fr", 0): 20.10,
        ("random", "g2fr", 1): 22.40, ("random", "adaptive", 1): 21.90, ("random", "nog2fr", 1): 22.00,
        ("random", "g2fr", 2): 20.70, ("random", "adaptive", 2): 20.95, ("random", "nog2fr", 2): 20.80}


def test_fewshot_table_gives_mean_std_per_view_set_and_the_paired_gap():
    """Rows (scene, view set); each cell mean ± sample std over seeds; per masked arm the paired PSNR gap
    to w/o (mean ± std) and in how many seeds it was >= w/o; the paper's numbers beside the fixed-β and w/o arms."""
    from statistics import mean, stdev

    from warpnerf.studies.tables import tables_markdown

    text = tables_markdown(_fewshot_results(PSNR))
    lines = text.splitlines()
    head = _cells(next(line for line in lines if line.startswith("| scene |")))
    assert head == ["scene", "view set", "PSNR w/ G2fR (fixed β)", "PSNR w/ G2fR (adaptive)", "PSNR w/o",
                    "SSIM w/ G2fR (fixed β)", "SSIM w/ G2fR (adaptive)", "SSIM w/o",
                    "LPIPS w/ G2fR (fixed β)", "LPIPS w/ G2fR (adaptive)", "LPIPS w/o",
                    "PSNR gap fixed β - w/o (seeds >= w/o)", "PSNR gap adaptive - w/o (seeds >= w/o)"]
    rows = {tuple(c[:2]): c for c in map(_cells, lines) if c[0] == "lego"}
    assert list(rows) == [("lego", "fps"), ("lego", "random")]
    paper = {"g2fr": {"psnr": "22.46", "ssim": "0.860", "lpips": "0.094"},
             "nog2fr": {"psnr": "19.85", "ssim": "0.826", "lpips": "0.184"}}
    for vs in ("fps", "random"):
        cells = rows[("lego", vs)][2:]
        expected = []
        for key, f, d in (("psnr", lambda p: p, 2), ("ssim", lambda p: p / 30, 3), ("lpips", lambda p: 1 / p, 3)):
            for arm in ("g2fr", "adaptive", "nog2fr"):
                v = [f(PSNR[(vs, arm, s)]) for s in (0, 1, 2)]
                cell = f"{mean(v):.{d}f} ± {stdev(v):.{d}f}"
                expected.append(f"{cell} ({paper[arm][key]})" if arm in paper else cell)
        for arm in ("g2fr", "adaptive"):
            gaps = [PSNR[(vs, arm, s)] - PSNR[(vs, "nog2fr", s)] for s in (0, 1, 2)]
            expected.append(f"{mean(gaps):+.2f} ± {stdev(gaps):.2f} ({sum(g >= 0 for g in gaps)}/3)")
        assert cells == expected, vs
    # the counts, by hand: fps fixed β >= w/o in seed 1 only, adaptive in all; random fixed β in 0 and 1
    assert rows[("lego", "fps")][-2].endswith("(1/3)") and rows[("lego", "fps")][-1].endswith("(3/3)")
    assert rows[("lego", "random")][-2].endswith("(2/3)") and rows[("lego", "random")][-1].endswith("(2/3)")
    note = next(line for line in lines if line.startswith("Ours"))
    assert "view sets fps (farthest-point" in note and "random (views drawn with each seed)" in note
    assert "seeds 0, 1, 2 (cells: mean ± sample std" in note and "The arms are paired" in note


def test_fewshot_table_shows_the_heldout_arm_as_its_own_column():
    from statistics import mean, stdev

    from warpnerf.studies.tables import tables_markdown

    psnr = {**PSNR, **{(vs, "heldout", s): v + 0.05 for (vs, arm, s), v in PSNR.items() if arm == "adaptive"}}
    text = tables_markdown(_fewshot_results(psnr, arms_=("g2fr", "adaptive", "heldout", "nog2fr")))
    lines = text.splitlines()
    head = _cells(next(line for line in lines if line.startswith("| scene |")))
    assert head[2:6] == ["PSNR w/ G2fR (fixed β)", "PSNR w/ G2fR (adaptive)", "PSNR w/ G2fR (held-out)", "PSNR w/o"]
    assert head[-3:] == ["PSNR gap fixed β - w/o (seeds >= w/o)", "PSNR gap adaptive - w/o (seeds >= w/o)",
                         "PSNR gap held-out - w/o (seeds >= w/o)"]
    fps = next(c for c in map(_cells, lines) if c[:2] == ["lego", "fps"])
    gaps = [psnr[("fps", "heldout", s)] - psnr[("fps", "nog2fr", s)] for s in (0, 1, 2)]
    assert fps[-1] == f"{mean(gaps):+.2f} ± {stdev(gaps):.2f} (3/3)"
    assert fps[4] == f"{mean(psnr[('fps', 'heldout', s)] for s in (0, 1, 2)):.2f} ± " \
                     f"{stdev([psnr[('fps', 'heldout', s)] for s in (0, 1, 2)]):.2f}"


def test_fewshot_gap_counts_only_seeds_where_both_arms_finished():
    from statistics import mean

    from warpnerf.studies.tables import tables_markdown

    text = tables_markdown(_fewshot_results(PSNR, arms_=("g2fr", "nog2fr"),
                                            fail={"lego_fewshot_ngp_nog2fr_s2", "lego_fewshot_ngp_g2fr_s1_random"}))
    rows = {c[1]: c for c in map(_cells, text.splitlines()) if c[0] == "lego"}
    assert len(rows["fps"]) == 2 + 3 * 2 + 1  # no adaptive columns when the arm was not run
    fps_gaps = [PSNR[("fps", "g2fr", s)] - PSNR[("fps", "nog2fr", s)] for s in (0, 1)]
    assert rows["fps"][-1].startswith(f"{mean(fps_gaps):+.2f} ± ") and rows["fps"][-1].endswith("(1/2)")
    assert rows["fps"][3].startswith(f"{mean([24.02, 23.98]):.2f} ± ")  # w/o PSNR over the two seeds that finished
    assert rows["random"][-1].endswith("(1/2)")
    assert "Failed runs (n/a): lego_fewshot_ngp_nog2fr_s2, lego_fewshot_ngp_g2fr_s1_random." in text


def test_fewshot_table_names_the_builtin_chair_and_gives_it_no_paper_numbers():
    from warpnerf.studies.tables import tables_markdown

    text = tables_markdown(_fewshot_results(PSNR, source="builtin", scene="chair"))
    rows = [c for c in map(_cells, text.splitlines()) if c[0].startswith("chair")]
    assert [c[:2] for c in rows] == [["chair (built-in procedural, not NeRF-synthetic chair)", "fps"],
                                     ["chair (built-in procedural, not NeRF-synthetic chair)", "random"]]
    # Tab. 3's chair (25.72 / 17.02) is not ours: no brackets in the metric cells (the last two: gaps, k/3)
    assert all("(" not in cell for c in rows for cell in c[1:-2]) and all(c[-1].endswith("/3)") for c in rows)
    assert "Built-in scenes are warpnerf's procedural renders" in text


def test_fewshot_single_seed_keeps_plain_numbers():
    from warpnerf.studies.sweep import RunResult, expand
    from warpnerf.studies.table import table_spec
    from warpnerf.studies.tables import tables_markdown

    spec = table_spec(["lego"], ["fewshot"], out="o")
    results = [RunResult(r, status="done", metrics={"psnr": 24.0 if r.arm == "g2fr" else 23.5, "ssim": 0.9,
                                                    "lpips": 0.1, "iters": 20}) for r in expand(spec)]
    row = next(c for c in map(_cells, tables_markdown(results).splitlines()) if c[0] == "lego")
    assert row == ["lego", "fps", "24.00 (22.46)", "23.50 (19.85)", "0.900 (0.860)", "0.900 (0.826)",
                   "0.100 (0.094)", "0.100 (0.184)", "+0.50 (1/1)"]


def test_table_flags_view_sets_and_arms():
    """`--view-sets` and `--arms` are comma lists checked when parsed; a bad value is one line, exit 2."""
    from warpnerf.cli.app import build_parser
    from warpnerf.studies.table import table_spec

    parser = build_parser()
    args = parser.parse_args(["table", "--seed", "0,1,2", "--view-sets", "fps,random", "--arms", "g2fr,nog2fr,adaptive"])
    assert (args.seed, args.view_sets, args.arms) == ([0, 1, 2], ["fps", "random"], ["g2fr", "nog2fr", "adaptive"])
    args = parser.parse_args(["table"])
    assert (args.view_sets, args.arms) == (["fps"], ["g2fr", "nog2fr"])
    spec = table_spec(["lego"], ["fewshot"], seed=[0, 1], view_sets=["fps", "random"], arms=["adaptive", "nog2fr"])
    assert (spec.view_sets, spec.arms, spec.seeds) == (["fps", "random"], ["adaptive", "nog2fr"], [0, 1])
    assert (table_spec(["lego"], ["pose"]).view_sets, table_spec(["lego"], ["pose"]).arms) == (["fps"], ["g2fr", "nog2fr"])


@pytest.mark.parametrize("flag,value,needle", [("--view-sets", "fps,bogus", "unknown view set 'bogus'"),
                                               ("--arms", "g2fr,fixed", "unknown arm 'fixed'"),
                                               ("--arms", "g2fr,g2fr", "distinct arms"),
                                               ("--view-sets", ",", "distinct view sets")])
def test_bad_table_flag_is_one_line_exit_2_before_any_training(flag, value, needle, capsys, tmp_path, monkeypatch):
    from warpnerf.cli import main
    from warpnerf.studies import sweep

    monkeypatch.setattr(sweep, "run_sweep", lambda *a, **k: pytest.fail("training started"))
    with pytest.raises(SystemExit) as exc:
        main(["table", "--scenes", "chair", "--out", str(tmp_path / "o"), flag, value])
    assert exc.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("warpnerf: error: argument " + flag) and needle in err[0]
    assert not (tmp_path / "o").exists()


TINY_FIELD = "builtin_resolution = 32\neval_max_views = 1\nheldout_every = 0\n" + TINY_FIELD_TOML


def test_table_command_trains_paired_view_sets_and_seeds(tmp_path, monkeypatch, capsys):
    """`warpnerf table --view-sets fps,random --seed 0,1 --arms g2fr,nog2fr` on the built-in chair (32 px,
    20 steps; ~20 s on 2 busy cores): eight runs; the arms of a (view set, seed) trained on the same views,
    fps on the same views for both seeds, random on other views per seed; the table has both rows."""
    import json

    from warpnerf.cli import main

    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    (tmp_path / "tiny.toml").write_text(TINY_FIELD)
    out = tmp_path / "o"
    code = main(["table", "--scenes", "chair", "--tasks", "fewshot", "--view-sets", "fps,random", "--seed", "0,1",
                 "--arms", "g2fr,nog2fr", "--iters", "20", "--config", str(tmp_path / "tiny.toml"), "--out", str(out),
                 "--quiet"])
    assert code == 0
    views = {}
    for vs, suffix in (("fps", ""), ("random", "_random")):
        for seed in (0, 1):
            for arm in ("g2fr", "nog2fr"):
                m = json.loads((out / f"chair_fewshot_ngp_{arm}_s{seed}{suffix}" / "metrics.json").read_text())
                assert (m["view_set"], m["seed"], m["g2fr"], m["g2fr_schedule"]) == (vs, seed, arm == "g2fr", "fixed")
                views[(vs, seed, arm)] = m["train_view_ids"]
    for vs in ("fps", "random"):
        for seed in (0, 1):
            assert views[(vs, seed, "g2fr")] == views[(vs, seed, "nog2fr")]  # paired: same views
    assert views[("fps", 0, "g2fr")] == views[("fps", 1, "g2fr")]
    assert views[("random", 0, "g2fr")] != views[("random", 1, "g2fr")]
    table = capsys.readouterr().out
    rows = [_cells(line) for line in table.splitlines() if line.startswith("| chair ")]
    assert [r[:2] for r in rows] == [["chair (built-in procedural, not NeRF-synthetic chair)", "fps"],
                                     ["chair (built-in procedural, not NeRF-synthetic chair)", "random"]]
    for r in rows:
        assert " ± " in r[2] and " ± " in r[3] and r[-1].endswith("/2)")
    assert (out / "table.md").read_text() in table
