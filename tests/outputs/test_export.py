"""Mesh and point-cloud export of a briefly trained built-in chair, checked against the true mesh."""

import numpy as np
import pytest
import torch

pytest.importorskip("skimage")
pytest.importorskip("plyfile")

from warpnerf.cli import main  # noqa: E402
from warpnerf.data.builtin import scene_mesh  # noqa: E402
from warpnerf.outputs import export as E  # noqa: E402

from chair_run import ITERS, RESOLUTION  # noqa: E402  (the session fixture chair_run is in conftest.py)


def test_sphere_mesh_from_an_analytic_density():
    """Marching cubes + orientation + colours on a field whose answer is known: a ball of radius 0.5."""

    class Ball(torch.nn.Module):
        def geometry(self, x, w=None):
            # a smooth step (so marching-cubes normals are accurate): sigma = 50 on the sphere |x| = 0.5
            return 100.0 * torch.sigmoid(20.0 * (0.5 - x.norm(dim=-1))), x  # features = position, so colour can be checked

        def density(self, x, w=None):
            return self.geometry(x)[0]

        def color(self, geo, d):
            return (d * 0.5 + 0.5)  # colour encodes the view direction

    from types import SimpleNamespace

    from warpnerf.geometry.rayspace import RaySpace
    from warpnerf.model.occupancy import OccupancyGrid

    tr = SimpleNamespace(field=Ball(), occupancy=OccupancyGrid((-1, -1, -1, 1, 1, 1), 8), device=torch.device("cpu"),
                         cfg=SimpleNamespace(iters=1, memory_budget_mb=4096), level_weights=lambda s: None,
                         scene=SimpleNamespace(ray_space=RaySpace()))
    verts, faces, colors = E.extract_mesh(tr, resolution=65, threshold=50.0)
    r = np.linalg.norm(verts, axis=-1)
    assert abs(r.mean() - 0.5) < 0.02 and r.std() < 0.02  # grid spacing 1/32
    tri = verts[faces].astype(np.float64)
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    assert volume == pytest.approx(4 / 3 * np.pi * 0.125, rel=0.05)  # positive: faces CCW seen from outside
    # colour = field colour along the inward normal: for a ball centred at 0 that is -x/|x|
    want = ((-verts / r[:, None]) * 0.5 + 0.5) * 255
    assert np.abs(colors.astype(float) - want).mean() < 8


def test_ply_round_trip(tmp_path):
    verts = np.random.default_rng(0).random((10, 3)).astype(np.float32)
    colors = (verts * 255).astype(np.uint8)
    faces = np.array([[0, 1, 2], [2, 3, 4]], np.int32)
    E.write_ply(str(tmp_path / "m.ply"), verts, colors, faces)
    v, c, f = E.read_ply(str(tmp_path / "m.ply"))
    assert np.array_equal(v, verts) and np.array_equal(c, colors) and np.array_equal(f, faces)


def test_chair_mesh_matches_the_true_mesh(chair_run, tmp_path, capsys):
    out = tmp_path / "chair.ply"
    assert main(["export", "--run", str(chair_run), "--what", "mesh", "--resolution", "96", "--threshold", "5",
                 "--out", str(out), "--quiet"]) == 0
    verts, colors, faces = E.read_ply(str(out))
    assert faces is not None and len(faces) > 1000
    true = scene_mesh("chair")
    lo, hi = true.bounds()
    size = float((hi - lo).max())  # 2.24 scene units (the chair's height)
    err = np.abs(np.concatenate([verts.min(0) - lo, verts.max(0) - hi])) / size
    # every face of the bounding box within 5 % of the chair's size of the true one
    assert err.max() < 0.05, err
    a = E.sample_surface(verts, faces, 20000)
    b = E.sample_surface(true.points, true.faces, 20000)
    d_ab, d_ba = E.chamfer_distance(a, b)
    chamfer = 0.5 * (d_ab + d_ba)
    print(f"chair mesh after {ITERS} steps at {RESOLUTION} px: bbox error {err.max():.3f} of the size, "
          f"Chamfer {chamfer:.4f} scene units (pred->true {d_ab:.4f}, true->pred {d_ba:.4f})")
    assert chamfer < 0.1  # 4.5 % of the chair's size; measured values are printed above
    # vertex colours come from the field: the chair is brown/red on white, not white
    assert colors.mean() < 230


def test_chair_point_cloud(chair_run, tmp_path):
    out = tmp_path / "points.ply"
    assert main(["export", "--run", str(chair_run), "--what", "points", "--scale", "0.5", "--max-points", "5000",
                 "--max-views", "12", "--out", str(out), "--quiet"]) == 0
    pts, colors, faces = E.read_ply(str(out))
    assert faces is None and 100 < len(pts) <= 5000
    lo, hi = scene_mesh("chair").bounds()
    # the points lie on the chair: nearly all inside its (slightly grown) bounding box
    inside = np.all((pts > lo - 0.15) & (pts < hi + 0.15), axis=1)
    assert inside.mean() > 0.95


def test_export_errors_are_one_line(chair_run, tmp_path, capsys):
    assert main(["export", "--run", str(chair_run), "--threshold", "1e9", "--resolution", "16", "--quiet"]) == 2
    assert "never crosses the iso-level" in capsys.readouterr().err


@pytest.mark.parametrize("argv, needle", [
    (["--resolution", "2000"], "lower --resolution"),  # a 2000^3 density grid: 64 GB
    (["--what", "points", "--scale", "1000"], "lower --scale"),  # 32000 x 32000 renders
])
def test_export_sizes_beyond_the_memory_budget_are_one_line(chair_run, capsys, argv, needle):
    from door import one_line_error, tree

    before = tree(chair_run)
    assert main(["export", "--run", str(chair_run), *argv, "--quiet"]) == 2
    one_line_error(capsys, "needs at least", "memory_budget_mb = 4096", needle)
    assert tree(chair_run) == before
