"""The reproduction table: layout, paper numbers beside ours, run reuse."""

from warpnerf.table import format_table


def arms(source="dataset", model="ngp"):
    w = {"psnr": 30.03, "ssim": 0.946, "rot_err_deg": 0.0697, "trans_err_x100": 0.497, "scene_source": source, "model": model}
    wo = {"psnr": 25.0, "ssim": 0.9, "rot_err_deg": 1.5, "trans_err_x100": 9.0, "scene_source": source, "model": model}
    return {"w/": w, "w/o": wo}


def test_pose_table_has_paper_numbers_for_the_model():
    text = format_table("pose", {"lego": arms()}, "ngp")
    header, rule, row = text.splitlines()
    assert header.count("|") == rule.count("|") == row.count("|") == 8  # scene + 3 metrics x 2 arms
    assert "0.070 (0.049)" in row and "1.500 (1.181)" in row and "30.03 (32.53)" in row
    mtrf = format_table("pose", {"lego": arms(model="mtrf")}, "mtrf").splitlines()[2]
    assert "0.070 (0.051)" in mtrf and "27.54" in mtrf


def test_builtin_scene_gets_no_paper_numbers():
    row = format_table("fewshot", {"chair": arms(source="builtin")}).splitlines()[2]
    assert "(" not in row and "30.03" in row  # the built-in chair is not NeRF-synthetic's chair
    row = format_table("fewshot", {"chair": arms()}).splitlines()[2]
    assert "30.03 (25.72)" in row


def test_missing_values_are_marked():
    row = format_table("fewshot", {"lego": {"w/": {"psnr": 25.0}}}).splitlines()[2]
    assert "n/a" in row
