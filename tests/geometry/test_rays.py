"""Pixels to rays: the inverse of projection, distortion included."""

from __future__ import annotations

import numpy as np

from dbb_capture.geometry.cameras import Intrinsics, project_points
from dbb_capture.geometry.rays import camera_rays, pixel_grid, pixel_rays
from dbb_capture.geometry.transforms import look_at


def test_camera_rays_invert_projection_with_distortion():
    intr = Intrinsics(640, 480, 520, 515, 322.3, 236.9, (-0.28, 0.09, 0.001, -0.0007, -0.01))
    px = pixel_grid(640, 480)[::37, ::41].reshape(-1, 2)
    rays = camera_rays(intr, px)
    pts = rays * 0.7  # points along each ray, camera frame = world frame here
    uv = project_points(pts, np.eye(4), intr)
    assert np.abs(uv - px).max() < 1e-3


def test_pixel_rays_pass_through_projected_points_with_distortion():
    intr = Intrinsics(40, 30, 50.0, 52.0, 19.3, 14.6, (0.05, -0.02, 0.001, -0.002, 0.0))
    c2w = look_at(np.array([2.0, 0.0, -1.0]), np.zeros(3), np.array([0, 0, -1.0]))
    pts = np.random.default_rng(0).uniform(-0.2, 0.2, (20, 3))
    uv = project_points(pts, c2w, intr)
    o, d = pixel_rays(intr, c2w)
    for p, (u, v) in zip(pts, uv):
        if not (0 <= u < intr.width - 1 and 0 <= v < intr.height - 1):
            continue
        dw = c2w[:3, :3] @ camera_rays(intr, np.array([[u, v]]))[0]
        want = (p - c2w[:3, 3]) / np.linalg.norm(p - c2w[:3, 3])
        assert np.degrees(np.arccos(np.clip(dw @ want, -1, 1))) < 1e-4
    assert o.shape == d.shape == (30, 40, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1, atol=1e-5)
    np.testing.assert_allclose(o, np.broadcast_to(c2w[:3, 3], o.shape), atol=1e-6)
