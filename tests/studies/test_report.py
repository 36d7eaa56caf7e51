"""Results records and the report rendered from them (warpnerf/runs/record.py, warpnerf/studies/report.py)."""

import json
import os
import statistics
import subprocess
import sys
import time

import pytest

from warpnerf.runs import record as R
from warpnerf.studies import report
from warpnerf.studies.paper import paper_numbers


def _run_folder(path, metrics: dict, config_toml: str) -> str:
    os.makedirs(path, exist_ok=True)
    with open(os.path.join(path, "metrics.json"), "w") as fh:
        json.dump(metrics, fh)
    with open(os.path.join(path, "config.toml"), "w") as fh:
        fh.write(config_toml)
    return str(path)


def _pose_metrics(seed, g2fr, rot, trans, psnr, scene="lego", source="dataset"):
    return {"scene": scene, "scene_source": source, "task": "pose", "model": "ngp", "g2fr": g2fr, "iters": 3000,
            "seed": seed, "rot_err_deg": rot, "rot_err_deg_barf": rot + 0.001, "trans_err_x100": trans, "psnr": psnr,
            "ssim": 0.9, "lpips": None,
            "n_train_views": 100, "train_seconds": 200.0, "render_seconds_per_view": 0.5, "threads": 2,
            "config_hash": "h", "heldout_history": [[0, 1.0]]}


def _record(tmp_path, name, runs, other_cores=0.01, kind="table"):
    cpu = {"wall_seconds": 10.0, "own_cpu_seconds": 19.0, "other_cores": other_cores,
           "alone": other_cores < R.ALONE_MAX_OTHER_CORES}
    rec = R.build_record(name, kind, ["table", "--scenes", "lego"], runs, cpu, threads=2)
    path = R.record_path(name, str(tmp_path / "docs" / "results"))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    return R.write_record(path, rec)


@pytest.mark.parametrize("name", ["../x", ".hidden", "a/b", "", "x.json", "a b"])
def test_record_names_cannot_leave_the_folder(name, tmp_path):
    with pytest.raises(R.RecordError):
        R.record_path(name, str(tmp_path))


def test_existing_record_is_refused_before_any_work(tmp_path):
    path = R.check_new_record("lego_full", str(tmp_path))
    assert path == os.path.join(str(tmp_path), "lego_full.json")
    with open(path, "w") as fh:
        fh.write("{}")
    with pytest.raises(R.RecordError, match="exists"):
        R.check_new_record("lego_full", str(tmp_path))
    assert R.check_new_record("lego_full", str(tmp_path), replace=True) == path


def test_record_round_trip_keeps_the_run_files(tmp_path):
    m = _pose_metrics(0, True, 0.05, 0.2, 32.0)
    run = _run_folder(tmp_path / "run", m, 'task = "pose"\nscene = "lego"\npose_noise = 0.15\n')
    files = R.read_run_files(run)
    assert files["config"] == {"task": "pose", "scene": "lego", "pose_noise": 0.15}
    assert files["metrics"]["heldout_history"] == [[0, 1.0]]  # the held-out curve: the epoch plots read it
    assert files["metrics"]["rot_err_deg"] == 0.05
    path = _record(tmp_path, "one", [files], kind="run")
    rec = R.load_record(path)
    assert rec["runs"][0] == json.loads(json.dumps(files))
    assert rec["command"] == "warpnerf table --scenes lego"
    assert rec["machine"]["cores"] == os.cpu_count() and rec["machine"]["threads"] == 2
    assert rec["date"].endswith("Z")


def test_a_broken_record_is_one_error(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "something else"}')
    with pytest.raises(R.RecordError, match="not a warpnerf record"):
        R.load_record(str(bad))
    bad.write_text("{not json")
    with pytest.raises(R.RecordError, match="not a readable record"):
        R.load_record(str(bad))


def test_cpu_meter_sees_another_process():
    """A separate process spinning for the whole window shows up as about one other core."""
    spinner = subprocess.Popen([sys.executable, "-c", "import time\nt=time.time()\nwhile time.time()-t<3: pass"])
    try:
        time.sleep(0.3)  # the interpreter has started and spins
        meter = R.CpuMeter().start()
        time.sleep(1.5)
        out = meter.stop()
    finally:
        spinner.wait()
    if out["other_cores"] is None:
        pytest.skip("no /proc/stat on this system")
    assert 0.6 <= out["other_cores"] <= 2.5
    assert out["alone"] is False


def test_cpu_meter_counts_own_work_as_own():
    """Busy work in this process is not 'other': the other share stays below what it burned."""
    meter = R.CpuMeter().start()
    t = time.process_time()
    while time.process_time() - t < 1.0:
        pass
    out = meter.stop()
    if out["other_cores"] is None:
        pytest.skip("no /proc/stat on this system")
    assert out["own_cpu_seconds"] >= 0.9
    # whatever else runs on the machine, our own second of CPU is not counted as someone else's
    assert out["other_cores"] * out["wall_seconds"] <= (os.cpu_count() * out["wall_seconds"]) - 0.9 + 0.05


def test_paper_table_means_seeds_and_sets_the_paper_beside(tmp_path):
    runs = [R.read_run_files(_run_folder(tmp_path / f"r{i}", m, 'task = "pose"\npose_noise = 0.15\n'))
            for i, m in enumerate([_pose_metrics(0, True, 0.040, 0.20, 32.0), _pose_metrics(1, True, 0.060, 0.10, 33.0),
                                   _pose_metrics(0, False, 1.0, 4.0, 30.0),
                                   _pose_metrics(0, True, 9.0, 9.0, 9.0, scene="chair", source="builtin")])]
    _record(tmp_path, "tab1", runs)
    rows = report.recorded_runs(R.load_records(str(tmp_path / "docs" / "results")))
    text = report.paper_table("pose", rows)
    lego = next(line for line in text.splitlines() if line.startswith("| lego"))
    mean, std = statistics.fmean([0.040, 0.060]), statistics.stdev([0.040, 0.060])
    paper = paper_numbers("lego", "pose", "ngp")
    # the paper's rotation errors are BARF's float32 metric: they sit beside ours in that metric
    cells = [c.strip() for c in lego.split("|")]
    assert cells[4:6] == [f"{mean:.3f} ± {std:.3f}", "1.000"]  # our unclamped metric: no bracket
    assert cells[6:8] == [f"{mean + 0.001:.3f} ± {std:.3f} ({paper['w/']['rot_err_deg']:.3f})",
                          f"1.001 ({paper['w/o']['rot_err_deg']:.3f})"]
    assert "seeds 0,1" in lego and "noise 0.15" in lego
    assert "chair" not in text  # a built-in scene is not the paper's chair
    assert "200k" not in text and "20k" in text  # the pose regime is quoted, not the few-shot one
    assert report.paper_table("fewshot", rows) == "No record yet."


def _fewshot_metrics(seed, arm, psnr, view_set="fps", scene="lego", source="dataset"):
    return {"scene": scene, "scene_source": source, "task": "fewshot", "model": "ngp", "g2fr": arm != "none",
            "g2fr_schedule": arm if arm in ("adaptive", "heldout") else "fixed", "iters": 1000, "seed": seed, "psnr": psnr,
            "ssim": 0.8, "lpips": None, "view_set": view_set, "eval_split": "test", "epochs": 3.0 + seed,
            "heldout_history": [[249, psnr - 2], [499, psnr - 1], [999, psnr]], "heldout_epochs": [1.0, 2.0, 3.0],
            "heldout_split": "val", "n_train_views": 10}


def test_fewshot_table_pairs_arms_by_seed_and_keeps_val_runs_out(tmp_path):
    psnr = {("fixed", 0): 24.0, ("fixed", 1): 25.0, ("fixed", 2): 23.0, ("none", 0): 23.5, ("none", 1): 25.2,
            ("none", 2): 22.0, ("adaptive", 0): 24.5, ("adaptive", 1): 25.5, ("adaptive", 2): 22.5}
    config = 'task = "fewshot"\nlog2_table_size = 17\nrandom_background = true\nlr_final_ratio = 1.0\n'
    runs = [R.read_run_files(_run_folder(tmp_path / f"{a}{s}", _fewshot_metrics(s, a, v), config))
            for (a, s), v in psnr.items()]
    chosen_on_val = {**_fewshot_metrics(0, "none", 99.0), "eval_split": "val"}
    runs.append(R.read_run_files(_run_folder(tmp_path / "val", chosen_on_val, config)))
    runs.append(R.read_run_files(_run_folder(tmp_path / "chair", _fewshot_metrics(0, "fixed", 20.0, scene="chair",
                                                                                   source="builtin"), config)))
    _record(tmp_path, "tab3", runs)
    rows = report.recorded_runs(R.load_records(str(tmp_path / "docs" / "results")))
    text = report.fewshot_table(rows)
    lego = next(line for line in text.splitlines() if "| lego |" in line)
    cells = [c.strip() for c in lego.strip("|").split("|")]
    paper = paper_numbers("lego", "fewshot", "ngp")
    fixed = [psnr[("fixed", s)] for s in range(3)]
    assert f"{statistics.fmean(fixed):.2f} ± {statistics.stdev(fixed):.2f} ({paper['w/']['psnr']:.2f})" in cells
    gaps = [psnr[("fixed", s)] - psnr[("none", s)] for s in range(3)]  # +0.5, -0.2, +1.0: paired by seed
    assert f"{statistics.fmean(gaps):+.2f} ± {statistics.stdev(gaps):.2f} (2/3 ≥ 0)" in cells
    adaptive = [psnr[("adaptive", s)] - psnr[("none", s)] for s in range(3)]
    assert f"{statistics.fmean(adaptive):+.2f} ± {statistics.stdev(adaptive):.2f} (3/3 ≥ 0)" in cells
    assert "99.00" not in text  # a run measured on val is a choice, not a result
    assert "chair (built-in procedural, not NeRF-synthetic chair)" in text
    curves = report.fewshot_curves(rows)
    ep, mean, std = curves["tab3: lego, fps"]["w/o (val, 3 seeds)"]
    base = [psnr[("none", s)] for s in range(3)]
    assert ep == [1.0, 2.0, 3.0] and mean[-1] == pytest.approx(statistics.fmean(base))
    assert std[-1] == pytest.approx(statistics.stdev(base))


def test_an_arm_recorded_later_pairs_with_its_base_records_baseline(tmp_path):
    """``warpnerf record NAME DIRS --pairs-with BASE``: an adaptive arm run after a finished table joins
    that table's rows and is paired, seed by seed, with BASE's baseline; a different regime does not pair."""
    config = 'task = "fewshot"\nlog2_table_size = 19\nrandom_background = false\nlr_final_ratio = 1.0\n'
    base = {("fixed", 0): 24.0, ("fixed", 1): 23.0, ("none", 0): 22.0, ("none", 1): 23.5}
    _record(tmp_path, "tab3", [R.read_run_files(_run_folder(tmp_path / f"{a}{s}", _fewshot_metrics(s, a, v), config))
                               for (a, s), v in base.items()])
    later = {0: 22.5, 1: 23.0}
    runs = [R.read_run_files(_run_folder(tmp_path / f"ad{s}", _fewshot_metrics(s, "adaptive", v), config))
            for s, v in later.items()]
    other = 'task = "fewshot"\nlog2_table_size = 17\nrandom_background = false\nlr_final_ratio = 1.0\n'
    runs.append(R.read_run_files(_run_folder(tmp_path / "ad17", _fewshot_metrics(0, "adaptive", 30.0), other)))
    R.write_record(R.record_path("tab3_adaptive", str(tmp_path / "docs" / "results")),
                   R.build_record("tab3_adaptive", "runs", ["record"], runs, {}, extra={"pairs_with": "tab3"}))
    rows = report.recorded_runs(R.load_records(str(tmp_path / "docs" / "results")))
    text = report.fewshot_table(rows)
    lines = [line for line in text.splitlines() if "| lego |" in line]
    assert len(lines) == 2  # the 2^19 rows joined; the 2^17 adaptive run stands alone, unpaired
    joined = next(line for line in lines if "2^19" in line)
    cells = [c.strip() for c in joined.strip("|").split("|")]
    assert cells[0] == "tab3 + tab3_adaptive"
    gaps = [later[s] - base[("none", s)] for s in (0, 1)]  # +0.5, -0.5
    assert f"{statistics.fmean(gaps):+.2f} ± {statistics.stdev(gaps):.2f} (1/2 ≥ 0)" in cells
    alone = next(line for line in lines if "2^17" in line)
    assert "n/a" in alone and "tab3_adaptive" in alone


def test_report_writes_and_check_catches_a_hand_edit(tmp_path, capsys):
    runs = [R.read_run_files(_run_folder(tmp_path / "main", {**_pose_metrics(0, True, 0.1, 0.1, 23.08),
                                                               "task": "fewshot", "scene": "chair"}, 'task = "fewshot"\n'))]
    _record(tmp_path, "main_command", runs, other_cores=0.5, kind="run")
    (tmp_path / "README.md").write_text(f"# x\n\n{report.BEGIN}\nold\n{report.END}\n\nmore\n")
    args = type("A", (), {"root": str(tmp_path), "records": None, "check": True})
    assert report.run_cli(args) == 1  # README's block and results.md are stale before the first render
    args.check = False
    assert report.run_cli(args) == 0
    args.check = True
    assert report.run_cli(args) == 0
    readme = (tmp_path / "README.md").read_text()
    assert "old" not in readme and readme.endswith("\n\nmore\n")
    assert "| [main_command](docs/results/main_command.json) |" in readme
    assert "| 23.08 |" in readme and "no (0.50)" in readme  # measured other-core share, not declared
    assert "| lego_full | NeRF-synthetic lego, all 100 views | no record |" in readme
    results = (tmp_path / "docs" / "results.md").read_text()
    assert "[main_command](results/main_command.json)" in results
    (tmp_path / "docs" / "results.md").write_text(results.replace("23.08", "25.00"))
    assert report.run_cli(args) == 1
    assert "stale" in capsys.readouterr().out


def test_readme_without_markers_is_an_error(tmp_path):
    with pytest.raises(R.RecordError, match="markers"):
        report.render_readme("# no markers\n", [])


def test_train_record_holds_the_run_folder_and_refuses_a_second_time(tmp_path, monkeypatch):
    """`train --record NAME` end to end on a tiny built-in scene: the record carries the run's own
    metrics.json and config.toml; the same name again fails in one line before any run folder exists."""
    from warpnerf.cli import main

    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    recs = tmp_path / "recs"
    args = ["train", "--scene", "chair", "--task", "fewshot", "--builtin-resolution", "48", "--iters", "10",
            "--eval-max-views", "1", "--video-frames", "0", "--quiet", "--records-dir", str(recs), "--record", "tiny"]
    assert main([*args, "--out", str(tmp_path / "run")]) == 0
    rec = R.load_record(str(recs / "tiny.json"))
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert rec["runs"][0]["metrics"] == metrics
    assert rec["runs"][0]["config"]["iters"] == 10 and rec["runs"][0]["config"]["task"] == "fewshot"
    assert rec["kind"] == "run" and rec["command"].startswith("warpnerf train --scene chair")
    assert isinstance(rec["cpu"]["other_cores"], float) or rec["cpu"]["other_cores"] is None
    assert main([*args, "--out", str(tmp_path / "run2")]) == 2
    assert not (tmp_path / "run2").exists()


def test_record_command_records_finished_runs_with_their_own_provenance(tmp_path, monkeypatch):
    """`warpnerf record NAME DIR...`: run folders trained without --record; each run's commit and CPU
    share are the ones it measured (metrics.json "code" and "cpu"), the busiest run decides 'alone'."""
    from warpnerf.cli import main

    code = {"commit": "a" * 40, "dirty": False}
    dirs = []
    for i, other in enumerate((0.02, 0.6)):
        m = {**_fewshot_metrics(i, "none", 24.0 + i), "code": code,
             "cpu": {"wall_seconds": 10.0, "own_cpu_seconds": 9.0, "other_cores": other, "alone": other < 0.1}}
        dirs.append(_run_folder(tmp_path / f"r{i}", m, 'task = "fewshot"\n'))
    recs = tmp_path / "recs"
    assert main(["record", "pilot", *dirs, "--records-dir", str(recs)]) == 0
    rec = R.load_record(str(recs / "pilot.json"))
    assert rec["kind"] == "runs" and rec["run_code"] == [code, code]
    assert rec["cpu"]["other_cores"] == 0.6 and rec["cpu"]["alone"] is False
    assert [r["metrics"]["psnr"] for r in rec["runs"]] == [24.0, 25.0]
    assert main(["record", "pilot", *dirs, "--records-dir", str(recs)]) == 2  # exists: refused, one line
    no_cpu = _run_folder(tmp_path / "old", _fewshot_metrics(0, "none", 20.0), 'task = "fewshot"\n')
    assert main(["record", "old", no_cpu, "--records-dir", str(recs)]) == 0
    assert R.load_record(str(recs / "old.json"))["cpu"]["alone"] is None  # not measured: unknown, not "alone"
    # --pairs-with names the record whose baseline the new arm pairs with: it must exist
    assert main(["record", "later", no_cpu, "--records-dir", str(recs), "--pairs-with", "nosuch"]) == 2
    assert not (recs / "later.json").exists()
    assert main(["record", "later", no_cpu, "--records-dir", str(recs), "--pairs-with", "pilot"]) == 0
    assert R.load_record(str(recs / "later.json"))["pairs_with"] == "pilot"


def test_pose_table_keeps_starts_and_records_apart(tmp_path):
    """An identity start (BARF's LLFF protocol) is another regime than noise: its runs get their own row."""
    noisy = _pose_metrics(0, True, 0.3, 0.4, 23.0, scene="fern")
    identity = {**_pose_metrics(0, True, 2.5, 2.8, 20.0, scene="fern"), "pose_init": "identity"}
    runs = [R.read_run_files(_run_folder(tmp_path / f"r{i}", m, 'task = "pose"\n'))
            for i, m in enumerate([noisy, identity])]
    _record(tmp_path, "fern", runs)
    rows = report.recorded_runs(R.load_records(str(tmp_path / "docs" / "results")))
    fern = [line for line in report.paper_table("pose", rows).splitlines() if line.startswith("| fern")]
    assert len(fern) == 2
    assert sum("start identity" in line and "| 2.500 |" in line for line in fern) == 1
    assert sum("start identity" not in line and "| 0.300 |" in line for line in fern) == 1


def _export_record(tmp_path, name, min_faces, counts, run_metrics):
    run = _run_folder(tmp_path / "lego_run", run_metrics, 'task = "full"\nscene = "lego"\n')
    export = {"what": "mesh", "run": run, "out": "mesh.ply", "resolution": 256, "threshold": 10.0,
              "min_component_faces": min_faces, "export_seconds": 12.3, "peak_rss_mb_load": 900.0,
              "peak_rss_mb": 1500.0, **counts}
    cpu = {"wall_seconds": 30.0, "own_cpu_seconds": 50.0, "other_cores": 1.2, "alone": False}
    rec = R.build_record(name, "export", ["export", "--run", run], [], cpu, threads=2,
                         extra={"export": export, "source_run": R.read_run_files(run)})
    path = R.record_path(name, str(tmp_path / "docs" / "results"))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    return R.write_record(path, rec)


def test_export_records_get_their_own_table_and_no_run_row(tmp_path):
    metrics = {"scene": "lego", "task": "full", "iters": 3400, "psnr": 31.234, "config_hash": "h"}
    _export_record(tmp_path, "lego_mesh", 100, {"vertices_before": 1234567, "faces_before": 2469000,
                                                "pieces_before": 1063, "vertices": 1200000, "faces": 2400000,
                                                "pieces": 10}, metrics)
    _export_record(tmp_path, "lego_mesh_all", 1, {"vertices_before": 1234567, "faces_before": 2469000,
                                                  "pieces_before": 1063, "vertices": 1234567, "faces": 2469000,
                                                  "pieces": 1063}, metrics)
    records = R.load_records(str(tmp_path / "docs" / "results"))
    assert [r["kind"] for r in records] == ["export", "export"] and report.recorded_runs(records) == []
    text = report.render_results(records, str(tmp_path / "docs" / "results"))
    section = text[text.index(f"## {report.EXPORTS_TITLE}"):]
    rows = [line for line in section.splitlines() if line.startswith("| [")]
    assert len(rows) == 2
    assert rows[0].startswith("| [lego_mesh](") and "lego full, 3400 iters, test PSNR 31.23" in rows[0]
    assert "| 1,234,567 → 1,200,000 | 2,469,000 → 2,400,000 | 1,063 → 10 |" in rows[0]
    assert "| 100 |" in rows[0] and "| 900, 1500 |" in rows[0] and "no (1.20)" in rows[0]
    assert "none (--keep-floaters)" in rows[1] and "| 1,063 → 1,063 |" in rows[1]
    # the runs table does not list the source run: the export trained nothing
    assert "No record yet." in text[text.index("## Every recorded run"):text.index("## " + report.TASK_TITLES["pose"])]
    # without export records the section is not there
    assert report.EXPORTS_TITLE not in report.render_results([], "docs/results")


def test_viewer_bench_records_get_their_own_table(tmp_path):
    run = _run_folder(tmp_path / "lego_run", {"scene": "lego", "task": "full", "iters": 100, "psnr": 20.0},
                      'task = "full"\nscene = "lego"\n')
    for name, cameras_only, first in (("viewer_decoded", False, 9.87), ("viewer_cameras", True, 2.04)):
        bench = {"what": "viewer", "run": run, "device": "cpu", "threads": 2, "repeats": 3,
                 "cameras_only": cameras_only, "scene": "lego", "scene_source": "dataset", "train_views": 100,
                 "test_views": 200, "image_size": [400, 400], "step": 100, "load_seconds_first": first,
                 "load_seconds_median": first - 0.5, "process_seconds_median": first + 3.0, "peak_rss_mb_max": 555.4}
        cpu = {"wall_seconds": 30.0, "own_cpu_seconds": 20.0, "other_cores": 0.01, "alone": True}
        rec = R.build_record(name, "bench", ["bench", "viewer", "--run", run], [], cpu, threads=2,
                             extra={"bench": bench, "source_run": R.read_run_files(run)})
        path = R.record_path(name, str(tmp_path / "docs" / "results"))
        os.makedirs(os.path.dirname(path), exist_ok=True)
        R.write_record(path, rec)
    records = R.load_records(str(tmp_path / "docs" / "results"))
    assert report.recorded_runs(records) == []
    text = report.render_results(records, str(tmp_path / "docs" / "results"))
    rows = [line for line in text[text.index(f"## {report.VIEWER_TITLE}"):].splitlines() if line.startswith("| [")]
    assert len(rows) == 2
    cams = next(r for r in rows if r.startswith("| [viewer_cameras]("))
    dec = next(r for r in rows if r.startswith("| [viewer_decoded]("))
    assert "| lego full, 100 iters | 100 + 200, 400x400 | cameras only | 2.04, 1.54 | 5.04 | 555 | 3 |" in cams
    assert "| images decoded | 9.87, 9.37 | 12.87 |" in dec and "yes" in dec
    assert report.VIEWER_TITLE not in report.render_results([], "docs/results")


def test_an_export_record_without_its_figures_is_refused(tmp_path):
    path = _export_record(tmp_path, "x", 100, {"vertices_before": 1, "faces_before": 1, "pieces_before": 1,
                                               "vertices": 1, "faces": 1, "pieces": 1}, {"psnr": 20.0})
    rec = json.loads(open(path).read())
    del rec["export"]
    with open(path, "w") as fh:
        json.dump(rec, fh)
    with pytest.raises(R.RecordError, match="export record without"):
        R.load_record(path)


def test_the_heldout_arm_is_its_own_column_with_its_parameters(tmp_path):
    """A held-out-schedule run is neither the fixed nor the adaptive arm: its own PSNR and gap columns, named
    with its window, checks averaged, min gain, drop and val views, between the adaptive arm and w/o; paired
    by seed."""
    config = 'task = "fewshot"\nlog2_table_size = 19\nrandom_background = false\nlr_final_ratio = 1.0\n'
    heldout = config + ("g2fr_heldout_window = 10\ng2fr_heldout_average = 3\ng2fr_heldout_min_gain = 0.1\n"
                        "g2fr_heldout_drop = 0.25\ng2fr_heldout_views = 4\n")
    adaptive = config + "g2fr_plateau_window = 10\ng2fr_plateau_tol = 0.5\n"
    psnr = {("none", 0): 22.0, ("none", 1): 23.5, ("fixed", 0): 24.0, ("fixed", 1): 23.0, ("adaptive", 0): 23.0,
            ("adaptive", 1): 22.0, ("heldout", 0): 22.5, ("heldout", 1): 23.25}
    cfg = {"heldout": heldout, "adaptive": adaptive}
    runs = [R.read_run_files(_run_folder(tmp_path / f"{a}{s}", _fewshot_metrics(s, a, v), cfg.get(a, config)))
            for (a, s), v in psnr.items()]
    _record(tmp_path, "tab3", runs)
    rows = report.recorded_runs(R.load_records(str(tmp_path / "docs" / "results")))
    text = report.fewshot_table(rows)
    head = [c.strip() for c in text.splitlines()[0].strip("|").split("|")]
    label = "w/ G2fR (held-out, window 10, mean of 3, gain 0.1, drop 0.25, 4 val views)"
    assert [h for h in head if h.startswith("PSNR ")] == [
        "PSNR w/ G2fR (fixed β)", "PSNR w/ G2fR (adaptive, window 10, tol 0.5)", f"PSNR {label}", "PSNR w/o",
        "PSNR gap G2fR (fixed β) − w/o", "PSNR gap G2fR (adaptive, window 10, tol 0.5) − w/o",
        f"PSNR gap {label.split(' ', 1)[1]} − w/o"]
    cells = [c.strip() for c in next(line for line in text.splitlines() if "| lego |" in line).strip("|").split("|")]
    gaps = [psnr[("heldout", s)] - psnr[("none", s)] for s in (0, 1)]  # +0.5, -0.25
    assert cells[-1] == f"{statistics.fmean(gaps):+.2f} ± {statistics.stdev(gaps):.2f} (1/2 ≥ 0)"
    assert report.g2fr_cell(report.arm_of({"g2fr": True, "g2fr_schedule": "heldout"}, {})) == "w/ (heldout ?/?/?/?/?)"
