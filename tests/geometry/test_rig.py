"""Rig kinds from poses alone: the focus of converging cameras, and object / forward-facing / 360 rigs."""

import numpy as np

from warpnerf.geometry.rig import classify_rig, optical_focus


def look_at(eyes, target, up=(0.0, 0.0, 1.0)):
    """(N, 3, 4) float64 OpenGL cameras at ``eyes`` looking at ``target`` ((3,) or (N, 3))."""
    eyes = np.asarray(eyes, np.float64)
    back = eyes - np.asarray(target, np.float64)
    back /= np.linalg.norm(back, axis=-1, keepdims=True)
    right = np.cross(up, back)
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    return np.stack([right, np.cross(back, right), back, eyes], axis=-1)


def sphere(n, seed=0):
    """(n, 3) unit vectors away from the poles (look_at's up stays defined)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(-0.9, 0.9, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], -1)


def ring(n, radius, z=0.0):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(a), radius * np.sin(a), np.full(n, z)], -1)


def test_focus_of_cameras_on_a_sphere_is_the_point_they_look_at():
    target = np.array([0.7, -1.2, 2.5])
    c2w = look_at(target + 3.0 * sphere(40), target)
    np.testing.assert_allclose(optical_focus(c2w), target, atol=1e-6)
    # the least-squares point, not a vote: aims off by a few degrees still land near it
    rng = np.random.default_rng(1)
    noisy = look_at(c2w[:, :, 3], target + rng.normal(0, 0.15, (40, 3)))
    assert np.linalg.norm(optical_focus(noisy) - target) < 0.1


def test_parallel_axes_have_no_focus():
    xs, ys = np.meshgrid(np.linspace(-1, 1, 4), np.linspace(-1, 1, 3))
    eyes = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], -1)
    c2w = np.concatenate([np.tile(np.eye(3), (len(eyes), 1, 1)), eyes[:, :, None]], 2)  # all look along -z
    assert optical_focus(c2w) is None


def test_object_rigs():
    """A ring and a hemisphere looking at a point, and a hand-held orbit aiming within ~5 deg."""
    rng = np.random.default_rng(2)
    centre = np.array([3.0, -2.0, 1.0])
    upper = sphere(100)
    upper[:, 2] = np.abs(upper[:, 2])
    rigs = {
        "ring": look_at(centre + ring(24, 4.0, 1.5), centre),
        "hemisphere": look_at(centre + 4.0 * upper, centre),
        "hand-held": look_at(centre + ring(30, 2.5, 1.0), centre + rng.normal(0, 0.12, (30, 3))),
    }
    for name, c2w in rigs.items():
        rig = classify_rig(c2w)
        assert rig.kind == "object", (name, rig.reason)
        assert rig.reason.startswith("object-centric: ") and "\n" not in rig.reason
        assert np.linalg.norm(rig.focus - centre) < 0.2, name


def test_forward_facing_rigs():
    """A planar grid all looking along -z, and an LLFF-like patch converging on a point 10 units away."""
    xs, ys = np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-0.6, 0.6, 4))
    eyes = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], -1)
    grid = np.concatenate([np.tile(np.eye(3), (len(eyes), 1, 1)), eyes[:, :, None]], 2)
    llff = look_at(eyes, [0.0, 0.0, -10.0], up=(0.0, 1.0, 0.0))
    for name, c2w in {"grid": grid, "llff": llff}.items():
        rig = classify_rig(c2w)
        assert rig.kind == "forward_facing", (name, rig.reason)
        assert rig.reason.startswith("forward-facing: ") and "\n" not in rig.reason
    assert classify_rig(grid).focus is None


def test_360_rigs():
    """Cameras on a small circle looking outward (their axes meet behind them), and random directions."""
    eyes = ring(16, 0.3)
    outward = look_at(eyes, 2 * eyes)
    rng = np.random.default_rng(3)
    scattered = look_at(rng.uniform(-1, 1, (40, 3)), rng.uniform(-5, 5, (40, 3)))
    for name, c2w in {"outward": outward, "scattered": scattered}.items():
        rig = classify_rig(c2w)
        assert rig.kind == "360", (name, rig.reason)
        assert rig.reason.startswith("360: ") and "\n" not in rig.reason
    assert classify_rig(outward).in_front == 0.0
