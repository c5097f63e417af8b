"""Pinhole cameras: resized images keep their pixel centres; intrinsics from OpenCV's matrix."""

from __future__ import annotations

import numpy as np

from dbb_capture.geometry.cameras import Intrinsics, scaled_intrinsics


def test_downscaled_intrinsics_keep_pixel_centres():
    s = scaled_intrinsics(Intrinsics(800, 800, 1000, 1000, 399.5, 399.5), 4)
    assert (s.width, s.height, s.fx, s.cx) == (200, 200, 250, 99.5)


def test_intrinsics_from_opencv_matrix():
    K = np.array([[500.0, 0, 319.5], [0, 505.0, 239.5], [0, 0, 1]])
    i = Intrinsics.from_matrix(640, 480, K, np.array([[0.1, -0.2, 0.001, 0.002, 0.03, 0.5]]))
    assert (i.fx, i.fy, i.cx, i.cy) == (500.0, 505.0, 319.5, 239.5) and i.dist == (0.1, -0.2, 0.001, 0.002, 0.03)
    np.testing.assert_array_equal(i.K, K)
