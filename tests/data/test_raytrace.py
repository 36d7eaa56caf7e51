"""kernels/raytrace.py: depth, alpha and shading of known primitives against closed forms."""

import numpy as np
import pytest

from warpnerf.data import builtin
from warpnerf.data.builtin import MeshRenderer, look_at
from warpnerf.data.builtin_meshes import SOLID, Material, MeshBuilder

ALBEDO = (0.5, 0.4, 0.3)


def _solid_builder():
    mb = MeshBuilder()
    mat = mb.material(Material(SOLID, ALBEDO))
    return mb, mat


def _expected_colour(normal, lit=True):
    """Closed-form shading of the SOLID material for a unit normal facing the camera."""
    n = np.asarray(normal, float)
    key = np.asarray(builtin.KEY_DIR) / np.linalg.norm(builtin.KEY_DIR)
    fill = np.asarray(builtin.FILL_DIR) / np.linalg.norm(builtin.FILL_DIR)
    light = builtin.AMBIENT + builtin.FILL_STRENGTH * max(n @ fill, 0.0)
    if lit:
        light += builtin.KEY_STRENGTH * max(n @ key, 0.0)
    return np.clip(np.asarray(ALBEDO) * light, 0.0, 1.0)


@pytest.fixture(scope="module")
def box_renderer():
    mb, mat = _solid_builder()
    mb.box((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), mat)
    return MeshRenderer(mb.build())


@pytest.mark.parametrize("eye,normal", [((0.0, 0.0, 4.0), (0, 0, 1)), ((4.0, 0.0, 0.0), (1, 0, 0))])
def test_box_depth_alpha_and_shading_match_closed_form(box_renderer, eye, normal):
    size, focal = 33, 20.0
    rgba, depth = box_renderer.render(look_at(np.array([eye])), size, size, focal)
    # Pixel centre offsets from the optical axis are (k - 16) / focal; the face at distance 3.5
    # spans |offset| * 3.5 <= 0.5, i.e. |k - 16| <= 2 (no pixel centre lies near the edge).
    k = np.arange(size) - 16
    inside = (np.abs(k)[:, None] <= 2) & (np.abs(k)[None, :] <= 2)
    assert np.array_equal(rgba[0, ..., 3], inside.astype(np.float32))
    # The face is a plane: depth is exact up to float32 ray arithmetic (measured max error 4.8e-7).
    np.testing.assert_allclose(depth[0][inside], 3.5, atol=1e-5)
    assert np.all(depth[0][~inside] == 0.0)
    assert np.all(rgba[0][~inside][:, :3] == 0.0)
    np.testing.assert_allclose(rgba[0][inside][:, :3], np.tile(_expected_colour(normal), (inside.sum(), 1)), atol=1e-6)


def test_sphere_depth_matches_analytic_intersection():
    mb, mat = _solid_builder()
    mb.sphere((0.0, 0.0, 0.0), 1.0, mat, segments=128)
    size, focal, cam_z = 40, 30.0, 3.0
    rgba, depth = MeshRenderer(mb.build()).render(look_at(np.array([[0.0, 0.0, cam_z]])), size, size, focal)
    off = (np.arange(size) + 0.5 - size / 2) / focal
    a, b = np.meshgrid(off, off[::-1], indexing="xy")  # image rows go down, camera y goes up
    # Ray (a, b, -1) from (0, 0, 3) hits |x| = 1 at t = (3 - sqrt(9 - 8 q)) / q, q = a^2 + b^2 + 1;
    # t is also the camera-z depth because the direction has z = -1.
    q = a * a + b * b + 1.0
    disc = 9.0 - 8.0 * q
    hit = disc > 0
    t = (cam_z - np.sqrt(np.where(hit, disc, 0.0))) / q
    # Away from the silhouette (grazing rays) the only error is the tessellation: chord sag
    # r (1 - cos(pi / 128)) = 3.0e-4 at normal incidence, more for oblique rays; measured max
    # 6.0e-4 over the 256 pixels with disc > 0.3.
    centre = disc > 0.3
    assert centre.sum() > 200
    np.testing.assert_allclose(depth[0][centre], t[centre], atol=1e-3)
    # Alpha matches the analytic mask except within the tessellation margin of the silhouette
    # (36 of 1600 pixels excluded; 0 mismatches measured).
    certain = np.abs(disc) > 0.02
    assert np.array_equal(rgba[0, ..., 3][certain] > 0, hit[certain])


def test_hard_shadow_removes_key_light():
    mb, mat = _solid_builder()
    mb.box((-1.0, -1.0, -0.1), (1.0, 1.0, 0.0), mat)  # floor plate, top face at z = 0
    key = np.asarray(builtin.KEY_DIR) / np.linalg.norm(builtin.KEY_DIR)
    c = 0.6 * key  # a small blocker on the way from the plate centre to the key light
    mb.box(c - 0.1, c + 0.1, mat)
    mesh = mb.build()
    # The camera looks at the plate centre from the side opposite the blocker, so the centre
    # pixel sees the plate, which the blocker hides from the key light.
    eye = np.array([[-1.5, 1.5, 2.0]])
    size, focal = 31, 40.0
    rgba, depth = MeshRenderer(mesh, shadows=True).render(look_at(eye), size, size, focal)
    shadowed = rgba[0, 15, 15]
    assert depth[0, 15, 15] == pytest.approx(np.linalg.norm(eye), abs=1e-5)  # the centre pixel sees the origin
    lit = MeshRenderer(mesh, shadows=False).render(look_at(eye), size, size, focal)[0][0, 15, 15]
    np.testing.assert_allclose(shadowed[:3], _expected_colour((0, 0, 1), lit=False), atol=1e-6)
    np.testing.assert_allclose(lit[:3], _expected_colour((0, 0, 1), lit=True), atol=1e-6)


def test_builtin_meshes_fit_the_box():
    for name in builtin.SCENES:  # the bounded ones (the unbounded garden has a ground and a sky)
        lo, hi = builtin.scene_mesh(name).bounds()
        assert np.all(lo >= -1.2) and np.all(hi <= 1.2), (name, lo, hi)
