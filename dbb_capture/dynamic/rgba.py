"""RGBA frames as the model sees them: premultiplied colour and alpha in [0, 1].

Colour where alpha is 0 is undefined in straight RGBA and must not count, so losses, metrics
and the model's frames are premultiplied; files and the stepper's output are straight.
"""

from __future__ import annotations

import numpy as np
import torch


def premultiply(rgba: torch.Tensor) -> torch.Tensor:
    """Straight RGBA (..., 4, H, W) -> premultiplied colour and alpha, same shape."""
    return torch.cat([rgba[..., :3, :, :] * rgba[..., 3:4, :, :], rgba[..., 3:4, :, :]], -3)


def straight(pm: torch.Tensor) -> torch.Tensor:
    """Premultiplied RGBA (B, 4, S, S) -> straight RGBA (colour undefined where alpha is ~0)."""
    a = pm[:, 3:4]
    return torch.cat([(pm[:, :3] / a.clamp(min=1e-4)).clamp(0.0, 1.0), a], 1)


def premultiplied(rgba: np.ndarray) -> np.ndarray:
    """Straight RGBA (..., S, S, 4) uint8 or float in [0, 1] -> premultiplied float32 (..., S, S, 4)."""
    x = rgba.astype(np.float32)
    if rgba.dtype == np.uint8:
        x /= 255.0
    return np.concatenate([x[..., :3] * x[..., 3:4], x[..., 3:4]], -1)
