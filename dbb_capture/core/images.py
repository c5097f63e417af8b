"""Small image helpers shared by the stages (numpy; straight RGBA unless a name says otherwise)."""

from __future__ import annotations

import numpy as np


def to_u8(img: np.ndarray) -> np.ndarray:
    """Floats in [0, 1] (any shape) -> uint8, rounded and clipped."""
    return np.clip(np.round(np.asarray(img) * 255), 0, 255).astype(np.uint8)


def resize_rgba(rgba: np.ndarray, size: int) -> np.ndarray:
    """Straight RGBA float (h, w, 4) -> (size, size, 4), averaging premultiplied colour (so the
    colour behind transparent pixels does not bleed in); area averaging down, bilinear up."""
    import cv2

    if rgba.shape[0] == size and rgba.shape[1] == size:
        return rgba
    pm = np.concatenate([rgba[..., :3] * rgba[..., 3:4], rgba[..., 3:4]], -1)
    interp = cv2.INTER_AREA if rgba.shape[0] > size else cv2.INTER_LINEAR
    pm = cv2.resize(pm, (size, size), interpolation=interp)
    a = pm[..., 3:4]
    return np.concatenate([np.where(a > 1e-6, pm[..., :3] / np.maximum(a, 1e-6), 0.0).clip(0, 1), a], -1)


def write_image(path, img: np.ndarray) -> None:
    """Write ``img`` (H, W) grey or (H, W, 3|4) in OpenCV's BGR(A) order as a PNG (fast
    compression); an unwritable path is a :class:`~.errors.DbbError`."""
    import cv2

    from .errors import DbbError

    if not cv2.imwrite(str(path), img, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise DbbError(f"cannot write {path}")
