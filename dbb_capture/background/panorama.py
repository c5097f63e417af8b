"""The far room as an equirectangular panorama around the object: where rays meet it, at a
sphere's radius or a depth panorama's."""

from __future__ import annotations

import numpy as np


def sphere_exit(ou: np.ndarray, du: np.ndarray, r: np.ndarray | float) -> np.ndarray:
    """Unit directions (N, 3) from the centre to where rays ``ou``, ``du`` (N, 3) (origins
    relative to the centre, unit directions) leave a centred sphere of radius ``r`` ((N,) or scalar)."""
    b = (ou * du).sum(-1)
    tf = -b + np.sqrt(np.clip(b * b - (ou * ou).sum(-1) + np.asarray(r, np.float64) ** 2, 0, None))
    q = ou + tf[:, None] * du
    return q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)


def equirect(q: np.ndarray, he: int, we: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel coordinates x (azimuth, unwrapped), y (N,) of unit directions ``q`` (N, 3) (texel centres at integers)."""
    x = (np.arctan2(q[:, 1], q[:, 0]) / (2 * np.pi) + 0.5) * we - 0.5
    y = (0.5 - np.arcsin(np.clip(q[:, 2], -1, 1)) / np.pi) * he - 0.5
    return x, y


def _sample_wrapped(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (N,) of a panorama ``img`` (He, We) at texel coordinates ``x`` (wraps), ``y``."""
    he, we = img.shape
    y = np.clip(y, 0, he - 1)
    x0, y0 = np.floor(x), np.minimum(np.floor(y), he - 2)
    fx, fy = x - x0, y - y0
    xi0 = x0.astype(np.int64) % we
    xi1, yi0 = (xi0 + 1) % we, y0.astype(np.int64)
    return ((img[yi0, xi0] * (1 - fx) + img[yi0, xi1] * fx) * (1 - fy)
            + (img[yi0 + 1, xi0] * (1 - fx) + img[yi0 + 1, xi1] * fx) * fy)


def env_coords(ou: np.ndarray, du: np.ndarray, r_out: float, he: int, we: int,
               depth: np.ndarray | None = None, iters: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Far-sphere texel coordinates x (unwrapped), y (N,) float32 where rays ``ou``, ``du`` (N, 3)
    (origins relative to the centre, unit directions; field basis) meet the room.

    Without ``depth`` the room is the sphere of radius ``r_out``; with ``depth`` (He, We) metres it
    is the depth panorama, met by fixed-point iteration from the sphere of radius ``r_out`` (hit
    the sphere at the depth found where the previous hit pointed; the map is smooth, so a few
    steps settle).
    """
    ou, du = np.asarray(ou, np.float64), np.asarray(du, np.float64)
    x, y = equirect(sphere_exit(ou, du, r_out), he, we)
    for _ in range(iters if depth is not None else 0):
        x, y = equirect(sphere_exit(ou, du, _sample_wrapped(depth, x, y)), he, we)
    return x.astype(np.float32), y.astype(np.float32)
