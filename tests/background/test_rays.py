"""Training rays: the room rays keep away from the matte."""

from __future__ import annotations

import numpy as np
from conftest import UP, ring_cameras, small_intrinsics

from dbb_capture.crops.camera import crop_camera


def test_room_rays_keep_away_from_the_matte():
    from dbb_capture.background.rays import room_rays

    center = np.array([0.3, 0.2, -0.08])
    cam = crop_camera(ring_cameras(center)[3], small_intrinsics(), center, 0.1, UP, 32, 0.9)
    obs = np.full((32, 32, 3), 128, np.uint8)
    alpha = np.zeros((32, 32), np.uint8)
    alpha[10:20, 10:20] = 255
    inside = np.full((32, 32), 255, np.uint8)
    inside[:, :4] = 0
    o, d, c = room_rays(cam, obs, alpha, inside, grow_px=2)
    assert len(o) == 28 * 32 - 14 * 14 and np.allclose(c, 128 / 255)
    assert len(room_rays(cam, obs, alpha, None, grow_px=0)[0]) == 32 * 32 - 100
