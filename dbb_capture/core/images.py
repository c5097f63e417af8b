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


# Report figures: labels drawn into the image itself, so a PNG explains itself wherever it goes.
LABEL_PX = 20               # height of a label band (pixels)
_LABEL_BG, _LABEL_FG = 40, 235


def fit_text(img: np.ndarray, text: str, x0: int, y0: int, w: int, h: int) -> None:
    """Draw ``text`` centred in the box (x0, y0, w, h) of ``img`` (H, W, 3) uint8, in place, at the
    largest size up to the report's that fits (light grey, so RGB and BGR images read alike)."""
    import cv2

    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.45
    while True:
        (tw, th), base = cv2.getTextSize(text, font, scale, 1)
        if (tw <= w - 4 and th + base <= h) or scale <= 0.25:
            break
        scale -= 0.05
    org = (x0 + max((w - tw) // 2, 2), y0 + (h + th) // 2 - 1)
    cv2.putText(img, text, org, font, scale, (_LABEL_FG,) * 3, 1, cv2.LINE_AA)


def label_band(labels: list[str], widths: list[int], height: int = LABEL_PX) -> np.ndarray:
    """A dark band (height, sum(widths), 3) uint8 with each label centred over its column."""
    band = np.full((height, int(sum(widths)), 3), _LABEL_BG, np.uint8)
    x = 0
    for text, w in zip(labels, widths):
        fit_text(band, text, x, 0, int(w), height)
        x += int(w)
    return band


def with_header(img: np.ndarray, labels: list[str], widths: list[int]) -> np.ndarray:
    """``img`` (H, W, 3) uint8 under a band naming its columns (``widths`` sum to at most W)."""
    widths = list(widths) + ([img.shape[1] - sum(widths)] if sum(widths) < img.shape[1] else [])
    return np.concatenate([label_band(list(labels) + [""] * (len(widths) - len(labels)), widths), img], 0)


def with_row_labels(img: np.ndarray, labels: list[str], heights: list[int], width: int = 110) -> np.ndarray:
    """``img`` (H, W, 3) uint8 beside a column of ``width`` px naming its rows (``heights`` from the top)."""
    col = np.full((img.shape[0], width, 3), _LABEL_BG, np.uint8)
    y = 0
    for text, h in zip(labels, heights):
        fit_text(col, text, 0, y, width, int(h))
        y += int(h)
    return np.concatenate([col, img], 1)


def upscale_nearest(img: np.ndarray, min_px: int, side: int | None = None) -> np.ndarray:
    """``img`` (H, W, ...) enlarged by the smallest whole factor that makes ``side`` pixels (default
    its shorter side; e.g. one frame of a grid) at least ``min_px``, repeating pixels (a report
    shows the model's pixels as they are)."""
    k = max(1, -(-int(min_px) // max(1, int(side or min(img.shape[:2])))))
    return img if k == 1 else np.repeat(np.repeat(img, k, 0), k, 1)
