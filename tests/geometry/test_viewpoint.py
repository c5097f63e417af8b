"""Viewpoints and the scene's up, from the data."""

from __future__ import annotations

import numpy as np

from dbb_capture.geometry.viewpoint import up_from_cameras


def test_up_from_cameras():
    c2w = np.stack([np.eye(4)] * 3)
    c2w[:, 2, 3] = [-0.5, -0.4, 0.1]
    assert np.allclose(up_from_cameras(c2w), [0, 0, -1])
    c2w[:, 2, 3] = [0.5, 0.4, -0.1]
    assert np.allclose(up_from_cameras(c2w), [0, 0, 1])
