"""Viewpoints and the scene's up, from the data."""

from __future__ import annotations

import numpy as np
import pytest

from dbb_capture.geometry.viewpoint import Viewpoint, eye_at, up_from_cameras, viewpoint


def test_up_from_cameras():
    c2w = np.stack([np.eye(4)] * 3)
    c2w[:, 2, 3] = [-0.5, -0.4, 0.1]
    assert np.allclose(up_from_cameras(c2w), [0, 0, -1])
    c2w[:, 2, 3] = [0.5, 0.4, -0.1]
    assert np.allclose(up_from_cameras(c2w), [0, 0, 1])


@pytest.mark.parametrize("up", [(0.0, 0.0, -1.0), (0.0, 0.0, 1.0)])
def test_eye_at_inverts_viewpoint(up):
    rng = np.random.default_rng(3)
    center, up = np.array([0.3, -0.1, -0.05]), np.array(up)
    for _ in range(20):
        vp = Viewpoint(rng.uniform(-179, 179), rng.uniform(-80, 80), rng.uniform(0.2, 2.0))
        back = viewpoint(eye_at(vp, center, up), center, up)
        assert np.allclose([back.azimuth_deg, back.elevation_deg, back.distance_m],
                           [vp.azimuth_deg, vp.elevation_deg, vp.distance_m], atol=1e-9)
