"""Image quality: PSNR and SSIM of arrays in [0, 1] (any channels: RGB, RGBA, premultiplied)."""

from __future__ import annotations

import math

import numpy as np


def psnr_from_mse(mse: float) -> float:
    """PSNR (dB) of a mean squared error of values in [0, 1] (at most 120 dB)."""
    return float(-10 * math.log10(max(float(mse), 1e-12)))


def psnr(pred: np.ndarray, truth: np.ndarray) -> float:
    """PSNR (dB) of two arrays of equal shape with values in [0, 1]."""
    return psnr_from_mse(float(np.mean((np.asarray(pred, np.float64) - truth) ** 2)))


def ssim(pred: np.ndarray, truth: np.ndarray) -> float:
    """SSIM of images (H, W, C) in [0, 1] (mean over channels; scikit-image's defaults)."""
    from skimage.metrics import structural_similarity

    return float(structural_similarity(pred, truth, channel_axis=-1, data_range=1.0))


def rms_levels(psnr_db: float) -> float:
    """The RMS error, in 8-bit levels (of 255), that a PSNR (dB, values in [0, 1]) stands for."""
    return 255.0 * 10 ** (-float(psnr_db) / 20)
