"""Rigid transforms as 4x4 matrices (numpy, float64)."""

from __future__ import annotations

import numpy as np


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4) without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 from rotation (3, 3) and translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.ravel(t)
    return T


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (4, 4) at ``eye`` looking at ``target``; image "up" toward ``up``.

    Camera +z points at the target and camera -y (image up) is as close to ``up`` as possible.
    """
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return rigid(np.stack([x, y, z], axis=1), eye)


def c2w_from_rvec_tvec(rvec, tvec) -> np.ndarray:
    """Camera-to-world (4, 4) of OpenCV's pose ``rvec`` (3,) Rodrigues, ``tvec`` (3,) (world to camera)."""
    import cv2

    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
    return invert_rigid(rigid(R, np.ravel(tvec)))
