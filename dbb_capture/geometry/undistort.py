"""Undistorted images: the same pinhole camera (size and K) without lens distortion."""

from __future__ import annotations

import cv2
import numpy as np

from .cameras import Intrinsics


class Undistorter:
    """Remaps frames of ``intr`` to the same pinhole without distortion (same size, same K)."""

    def __init__(self, intr: Intrinsics):
        self.intr = intr
        self.target = intr.undistorted()
        self._maps = None
        if intr.distorted:
            self._maps = cv2.initUndistortRectifyMap(intr.K, intr.dist_array, None, intr.K,
                                                     (intr.width, intr.height), cv2.CV_16SC2)

    def __call__(self, img: np.ndarray) -> np.ndarray:
        """(H, W, C) image -> undistorted (H, W, C); pixels with no source stay black."""
        if self._maps is None:
            return img
        return cv2.remap(img, self._maps[0], self._maps[1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT)
