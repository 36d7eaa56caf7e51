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
    mesh = E.extract_mesh(tr, resolution=65, threshold=50.0)
    verts, faces, colors = mesh.verts, mesh.faces, mesh.colors
    assert "1 pieces" in mesh.summary
    r = np.linalg.norm(verts, axis=-1)
    assert abs(r.mean() - 0.5) < 0.02 and r.std() < 0.02  # grid spacing 1/32
    tri = verts[faces].astype(np.float64)
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    assert volume == pytest.approx(4 / 3 * np.pi * 0.125, rel=0.05)  # positive: faces CCW seen from outside
    # colour = field colour along the inward normal: for a ball centred at 0 that is -x/|x|
    want = ((-verts / r[:, None]) * 0.5 + 0.5) * 255
    assert np.abs(colors.astype(float) - want).mean() < 8
    # the written normals point outwards: along x / |x| for the ball
    assert np.einsum("ij,ij->i", mesh.normals, verts / r[:, None]).min() > 0.9


def _cube(origin, size=1.0):
    """Vertices (8, 3) and triangles (12, 3) of an axis-aligned cube, counter-clockwise seen from outside."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)  # index 4x + 2y + z
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return np.asarray(origin, np.float64) + size * corners, faces


def test_cube_faces_and_vertex_normals_point_outwards():
    verts, faces = _cube((0, 0, 0), 2.0)
    tri = verts[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward = tri.mean(1) - 1.0  # centroid minus the cube's centre
    # each face normal is the axis direction of its side: parallel to the centroid offset's largest axis
    side = np.eye(3)[np.abs(outward).argmax(1)] * np.sign(outward)
    assert np.allclose(face_n / np.linalg.norm(face_n, axis=1, keepdims=True), side)
    n = E.vertex_normals(verts, faces)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    assert np.array_equal(np.sign(n), np.sign(verts - 1.0))  # each corner's normal points into its octant
    # closed form on an octahedron: four equal faces around each vertex, so the normal is the vertex direction
    ov = np.concatenate([np.eye(3), -np.eye(3)])
    of = np.array([(0, 1, 2), (1, 3, 2), (3, 4, 2), (4, 0, 2), (1, 0, 5), (3, 1, 5), (4, 3, 5), (0, 4, 5)])
    assert np.allclose(E.vertex_normals(ov, of), ov, atol=1e-6)


def test_floaters_are_removed_by_piece_size():
    va, fa = _cube((0, 0, 0))
    vb, fb = _cube((3, 0, 0))
    extra = np.array([[9, 9, 9], [9, 9.1, 9], [9, 9, 9.1],  # 16-18: a lone triangle
                      [5, 5, 5], [5, 5.1, 5], [5, 5, 5.1], [5.1, 5, 5], [5.1, 5.1, 5],  # 19-23: two triangles, one shared vertex
                      [-0.1, 0, 0], [-0.1, -0.1, 0],  # 24-25: a triangle hanging off cube A's vertex 0
                      [7, 7, 7]], np.float64)  # 26: in no face
    verts = np.concatenate([va, vb, extra])
    faces = np.concatenate([fa, fb + 8, [(16, 17, 18), (19, 20, 21), (19, 22, 23), (0, 24, 25)]])
    label, n = E.face_components(faces, len(verts))
    # by hand: cube A + its hanging triangle (13 faces), cube B (12), the lone triangle (1), the pair (2)
    assert n == 4 and sorted(np.bincount(label)) == [1, 2, 12, 13]
    keep, kept, (before, after) = E.remove_small_components(faces, len(verts), 2)
    assert (before, after) == (4, 3) and len(kept) == 27 and len(keep) == 8 + 2 + 8 + 5
    keep, kept, (before, after) = E.remove_small_components(faces, len(verts), 5)
    assert after == 2 and len(kept) == 25 and sorted(keep) == list(range(16)) + [24, 25]
    # re-indexed faces name the same points
    assert {tuple(map(tuple, t)) for t in verts[keep][kept]} == \
        {tuple(map(tuple, t)) for t in verts[np.concatenate([fa, fb + 8, [(0, 24, 25)]])]}
    # nothing is large enough: the largest piece stays
    _, kept, (_, after) = E.remove_small_components(faces, len(verts), 100)
    assert after == 1 and len(kept) == 13
    _, kept, (_, after) = E.remove_small_components(faces, len(verts), 1)
    assert after == 4 and len(kept) == len(faces)


def test_ply_round_trip(tmp_path):
    verts = np.random.default_rng(0).random((10, 3)).astype(np.float32)
    colors = (verts * 255).astype(np.uint8)
    faces = np.array([[0, 1, 2], [2, 3, 4]], np.int32)
    E.write_ply(str(tmp_path / "m.ply"), verts, colors, faces)
    v, c, f = E.read_ply(str(tmp_path / "m.ply"))
    assert np.array_equal(v, verts) and np.array_equal(c, colors) and np.array_equal(f, faces)
    assert E.read_ply_normals(str(tmp_path / "m.ply")) is None
    normals = -verts
    E.write_ply(str(tmp_path / "n.ply"), verts, colors, faces, normals)
    v, c, f = E.read_ply(str(tmp_path / "n.ply"))
    assert np.array_equal(v, verts) and np.array_equal(c, colors) and np.array_equal(f, faces)
    assert np.array_equal(E.read_ply_normals(str(tmp_path / "n.ply")), normals)


def test_chair_mesh_matches_the_true_mesh(chair_run, tmp_path, capsys):
    out = tmp_path / "chair.ply"
    assert main(["export", "--run", str(chair_run), "--what", "mesh", "--resolution", "96", "--threshold", "5",
                 "--out", str(out), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "pieces" in said and "iso-level 5" in said, said
    verts, colors, faces = E.read_ply(str(out))
    assert faces is not None and len(faces) > 1000
    label, n = E.face_components(faces, len(verts))
    assert n == 1 or np.bincount(label).min() >= E.DEFAULT_MIN_COMPONENT_FACES  # no floater left
    # unit vertex normals that agree with the (outward, CCW) faces around them
    normals = E.read_ply_normals(str(out))
    assert normals is not None and np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-4)
    tri = verts[faces].astype(np.float64)
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (np.einsum("ij,ij->i", face_n, normals[faces].sum(1)) > 0).mean() > 0.95
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
    assert main(["export", "--run", str(chair_run), "--keep-floaters", "--min-component-faces", "5", "--quiet"]) == 2
    assert "leave out --min-component-faces" in capsys.readouterr().err


def test_export_keep_floaters(chair_run, tmp_path, capsys):
    out = tmp_path / "all.ply"
    assert main(["export", "--run", str(chair_run), "--resolution", "48", "--threshold", "5", "--keep-floaters",
                 "--out", str(out), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "floaters kept" in said, said
    verts, _, faces = E.read_ply(str(out))
    assert f"{len(verts):,} vertices, {len(faces):,} faces" in said


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


def test_export_writes_its_counts_and_records_them(chair_run, tmp_path, capsys):
    """``<out>.export.json`` and ``--record``: the counts are the written PLY's, and the floaters-kept export's
    counts are the default export's counts before removal (the same marching cubes)."""
    import json

    from warpnerf.runs import record as R

    records = tmp_path / "records"
    common = ["export", "--run", str(chair_run), "--resolution", "48", "--threshold", "5", "--quiet",
              "--records-dir", str(records)]
    assert main([*common, "--out", str(tmp_path / "m.ply"), "--record", "chair_mesh"]) == 0
    assert main([*common, "--out", str(tmp_path / "all.ply"), "--keep-floaters", "--record", "chair_mesh_all"]) == 0
    assert "record: " in capsys.readouterr().out
    rec, rec_all = (R.load_record(str(records / f"{n}.json")) for n in ("chair_mesh", "chair_mesh_all"))
    for r, ply in ((rec, "m.ply"), (rec_all, "all.ply")):
        e = r["export"]
        assert r["kind"] == "export" and r["runs"] == [] and r["command"].startswith("warpnerf export --run ")
        assert e == json.loads((tmp_path / ply.replace(".ply", ".export.json")).read_text())
        verts, _, faces = E.read_ply(str(tmp_path / ply))
        assert (e["vertices"], e["faces"], e["pieces"]) == (len(verts), len(faces), E.face_components(faces, len(verts))[1])
        assert e["peak_rss_mb"] > 0 and e["peak_rss_mb_load"] > 0 and e["export_seconds"] >= 0
        assert r["source_run"]["metrics"] == json.loads((chair_run / "metrics.json").read_text())
    e, e_all = rec["export"], rec_all["export"]
    assert e["min_component_faces"] == E.DEFAULT_MIN_COMPONENT_FACES and e_all["min_component_faces"] == 1
    for key in ("vertices", "faces", "pieces"):
        assert e_all[key] == e_all[f"{key}_before"] == e[f"{key}_before"] >= e[key]


def test_export_record_name_is_checked_before_any_work(chair_run, tmp_path, capsys):
    out = tmp_path / "m.ply"
    assert main(["export", "--run", str(chair_run), "--resolution", "16", "--out", str(out), "--quiet",
                 "--record", "../escape", "--records-dir", str(tmp_path)]) == 2
    assert "record name" in capsys.readouterr().err
    assert not out.exists()
