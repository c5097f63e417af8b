"""The pixels of dataset frames: straight RGBA or RGB float images, optionally shrunk."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..geometry.cameras import Intrinsics, scaled_intrinsics
from .records import Frame


def load_rgba(frame: Frame, downscale: float = 1.0) -> np.ndarray:
    """Straight RGBA float32 (h, w, 4) in [0, 1] at 1/``downscale`` size.

    Images without alpha get alpha 1 unless the frame has a mask (black = transparent).
    Resizing averages premultiplied colour so edges keep their true colour.
    """
    import cv2

    img = _read_image(frame.image_path, cv2.IMREAD_UNCHANGED, frame.intr)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    img = img.astype(np.float32) / scale
    rgb = img[..., 2::-1] if img.shape[2] >= 3 else img
    alpha = img[..., 3:4] if img.shape[2] == 4 else np.ones_like(img[..., :1])
    if frame.mask_path is not None:
        m = cv2.imread(str(frame.mask_path), cv2.IMREAD_GRAYSCALE)
        if m is None or m.shape != img.shape[:2]:
            raise InputError(f"mask {frame.mask_path} is unreadable or not the image's size")
        alpha = alpha * (m[..., None].astype(np.float32) / 255.0)
    rgba = _area_downscale(np.concatenate([rgb * alpha, alpha], axis=-1), frame.intr, downscale)
    a = rgba[..., 3:4]
    rgb = np.where(a > 1e-6, rgba[..., :3] / np.maximum(a, 1e-6), 0.0)
    return np.ascontiguousarray(np.concatenate([np.clip(rgb, 0, 1), a], -1), dtype=np.float32)


def load_rgb(path: Path, intr: Intrinsics, downscale: float = 1.0) -> np.ndarray:
    """An RGB image float32 (h, w, 3) in [0, 1] of a frame with intrinsics ``intr``, at
    1/``downscale`` size (area-averaged), e.g. a crop's observed pixels or predicted room."""
    import cv2

    rgb = _read_image(path, cv2.IMREAD_COLOR, intr)[..., ::-1].astype(np.float32) / 255.0
    return np.ascontiguousarray(_area_downscale(rgb, intr, downscale), dtype=np.float32)


def _read_image(path: Path, flags: int, intr: Intrinsics) -> np.ndarray:
    """``cv2.imread`` of a frame's image, which must be ``intr``'s size (clear errors otherwise)."""
    import cv2

    img = cv2.imread(str(path), flags)
    if img is None:
        raise InputError(f"cannot read image {path}")
    if (img.shape[1], img.shape[0]) != (intr.width, intr.height):
        raise InputError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, dataset says {intr.width}x{intr.height}")
    return img


def _area_downscale(img: np.ndarray, intr: Intrinsics, downscale: float) -> np.ndarray:
    """``img`` (h, w, C) float32 of a frame with intrinsics ``intr`` at 1/``downscale`` size (area average)."""
    if downscale == 1:
        return img
    import cv2

    target = scaled_intrinsics(intr, downscale)
    return cv2.resize(img, (target.width, target.height), interpolation=cv2.INTER_AREA)
