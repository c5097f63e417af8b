"""Preview cameras agree with the viewpoint convention."""

from __future__ import annotations

import numpy as np
import pytest

from dbb_capture.bundle.previews import orbit_view


def test_preview_orbit_agrees_with_the_viewpoint_convention():
    from dbb_capture.bundle.proxy import bundle_from_board
    from dbb_capture.geometry.viewpoint import viewpoint

    c = np.array([0.4, 0.1, -0.09])
    for up in (np.array([0, 0, -1.0]), np.array([0, 0, 1.0])):
        T = bundle_from_board(c, up)
        for a, e in ((0.0, 20.0), (75.0, 45.0), (-130.0, 10.0)):
            v = orbit_view("x", T, 0.1, a, e, 0.5)
            p = viewpoint(v.c2w[:3, 3], c, up)
            assert (p.azimuth_deg, p.elevation_deg, p.distance_m) == pytest.approx((a, e, 0.5), abs=1e-6)
            assert np.allclose(v.c2w[:3, 2], (c - v.c2w[:3, 3]) / 0.5)     # looks at the centre
