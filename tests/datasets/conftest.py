"""A distorted camera, camera poses looking at the origin, and small images."""

from __future__ import annotations

import math

import cv2
import numpy as np

from dbb_capture.geometry.cameras import Intrinsics
from dbb_capture.geometry.transforms import look_at

INTR = Intrinsics(40, 30, 50.0, 52.0, 19.3, 14.6, (0.05, -0.02, 0.001, -0.002, 0.0))


def write_image(path, rgba=True, value=200):
    img = np.full((30, 40, 4 if rgba else 3), value, np.uint8)
    if rgba:
        img[..., 3] = 255
        img[:10, :, 3] = 0
    cv2.imwrite(str(path), img)


def poses_around(n=4):
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n
        out.append(look_at(np.array([2 * math.cos(a), 2 * math.sin(a), -1.0]), np.zeros(3), np.array([0, 0, -1.0])))
    return out
