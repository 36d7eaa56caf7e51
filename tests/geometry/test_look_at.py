"""One look_at: the built-in scene generator's numpy look_at is cameras.look_at, degenerate case included."""

import numpy as np
import torch

from warpnerf.data import builtin
from warpnerf.geometry.cameras import look_at


def test_builtin_look_at_is_cameras_look_at():
    # a ring, plus cameras straight above and below the target (view direction parallel to up)
    phi = np.linspace(0, 2 * np.pi, 7, endpoint=False)
    eyes = np.concatenate([np.stack([3 * np.cos(phi), 3 * np.sin(phi), np.full(7, 1.5)], -1),
                           [[0.0, 0.0, 3.0], [0.0, 0.0, -2.0]]])
    ours = builtin.look_at(eyes)
    ref = look_at(torch.from_numpy(eyes)).numpy()
    assert ours.dtype == np.float32 and ours.shape == (9, 3, 4)
    np.testing.assert_allclose(ours, ref, atol=1e-7)
    for c2w in ours:
        R = c2w[:, :3].astype(np.float64)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
        assert np.linalg.det(R) > 0
        # OpenGL: the camera looks down -z, at the target
        np.testing.assert_allclose(-R[:, 2], -c2w[:, 3] / np.linalg.norm(c2w[:, 3]), atol=1e-6)
    # no roll on the ring: the camera x axis is horizontal
    np.testing.assert_allclose(ours[:7, 2, 0], 0.0, atol=1e-7)
