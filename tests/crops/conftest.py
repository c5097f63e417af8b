"""A distorted source camera and camera poses around an object centre."""

from __future__ import annotations

import numpy as np

from dbb_capture.geometry.cameras import Intrinsics
from dbb_capture.geometry.transforms import look_at

UP = np.array([0.0, 0.0, -1.0])


SRC = Intrinsics(640, 480, 520.0, 522.0, 321.4, 238.2, (-0.25, 0.07, 0.0006, -0.0004, -0.008))


def camera_pose(center, az, el, dist, roll_deg):
    import cv2

    a, e = np.radians(az), np.radians(el)
    eye = center + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), 0]) + dist * np.sin(e) * UP
    # Aim a little off the object so it is not at the image centre, and roll the camera.
    c2w = look_at(eye, center + np.array([0.03, -0.02, 0.01]), UP)
    c2w[:3, :3] = c2w[:3, :3] @ cv2.Rodrigues(np.array([0, 0, np.radians(roll_deg)]))[0]
    return c2w


POSES = [(-60, 15, 0.5, 4), (0, 45, 0.7, -3), (50, 70, 0.9, 6), (120, 30, 0.6, -8)]
