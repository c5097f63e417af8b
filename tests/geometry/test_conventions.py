"""Camera conventions: OpenCV <-> OpenGL camera-to-world."""

from __future__ import annotations

import numpy as np

from dbb_capture.geometry.conventions import opencv_from_opengl, opengl_from_opencv
from dbb_capture.geometry.transforms import look_at


def test_opengl_opencv_round_trip_and_axes():
    c2w = look_at(np.array([0.1, -0.5, -0.4]), np.zeros(3), np.array([0, 0, -1.0]))
    gl = opengl_from_opencv(c2w)
    assert np.allclose(opencv_from_opengl(gl), c2w)
    # OpenGL cameras look along their -z; OpenCV along +z: same world direction.
    assert np.allclose(-gl[:3, 2], c2w[:3, 2])
    assert np.allclose(gl[:3, 3], c2w[:3, 3])
