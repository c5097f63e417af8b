"""Rigid transforms: look_at and the rigid inverse."""

from __future__ import annotations

import numpy as np

from dbb_capture.geometry.cameras import Intrinsics, project_points
from dbb_capture.geometry.transforms import invert_rigid, look_at


def test_look_at_keeps_image_up_toward_up():
    up = np.array([0, 0, -1.0])
    c2w = look_at(np.array([0.3, -0.6, -0.5]), np.array([0.1, 0.1, 0.0]), up)
    R = c2w[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1)
    # Image up is camera -y; it must have a positive component along the world up.
    assert (-R[:, 1]) @ up > 0.5
    # The target projects to the principal point.
    intr = Intrinsics(640, 480, 500, 500, 319.5, 239.5)
    uv = project_points(np.array([0.1, 0.1, 0.0]), c2w, intr)
    assert np.allclose(uv, [319.5, 239.5], atol=1e-9)


def test_invert_rigid():
    c2w = look_at(np.array([1.0, 2, 3]), np.zeros(3), np.array([0, 0, 1.0]))
    assert np.allclose(invert_rigid(c2w) @ c2w, np.eye(4), atol=1e-12)
