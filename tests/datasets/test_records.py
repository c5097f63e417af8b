"""Tests of dbb_capture.datasets.records."""

from __future__ import annotations

import numpy as np

from dbb_capture.datasets.records import Frame, estimate_volume

from .conftest import INTR, poses_around


def test_estimated_volume_holds_the_look_at_point():
    frames = [Frame(str(i), None, c2w, INTR) for i, c2w in enumerate(poses_around(6))]
    v = estimate_volume(frames)
    assert v.estimated and np.linalg.norm(v.center) < 1e-6 and 0.3 < v.radius < 2.3
