"""A smooth handheld-like camera path around the object, looking at it."""

from __future__ import annotations

import cv2
import numpy as np

from ..geometry.transforms import look_at
from .objects import UP
from .scene import Scene, SynthConfig


def _smooth_signal(rng: np.random.Generator, t: np.ndarray, seconds: float,
                   n: int = 4, fast: float = 1.0) -> np.ndarray:
    """A smooth random signal in [-1, 1]: a few sinusoids, slowest about one cycle per capture."""
    base = 1.0 / max(seconds, 1.0)
    out = np.zeros_like(t)
    total = 0.0
    for i in range(n):
        f = base * fast * (1 + i * 1.7) * rng.uniform(0.8, 1.25)
        a = 1.0 / (1 + i) ** 1.3
        out += a * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
        total += a
    return out / total


def camera_path(cfg: SynthConfig, scene: Scene, times: np.ndarray, rng: np.random.Generator):
    """OpenCV camera-to-world poses (N, 4, 4) of a handheld camera circling the object.

    Azimuth about the up axis (0 = in front of the object, on the board's -y side), elevation
    above the table and distance from the object centre follow slow random sinusoids; a few
    degrees of roll and millimetre jitter make it handheld.
    """
    T = cfg.seconds
    c_obj = scene.obj_sphere[0]
    target0 = c_obj + 0.4 * (scene.board.center - c_obj)
    a_lo, a_hi = cfg.azimuth_range_deg
    e_lo, e_hi = cfg.elevation_range_deg
    d_lo, d_hi = cfg.distance_range_m
    def sweep(cycles: float) -> np.ndarray:
        # Eased triangle wave in [-1, 1] from a random phase: every capture visits the whole range.
        tri = 4 * np.abs(((times / max(T, 1e-6)) * cycles + rng.uniform(0, 1)) % 1.0 - 0.5) - 1
        return np.sin(tri * np.pi / 2)

    az = np.radians(a_lo + (a_hi - a_lo) * 0.5 * (1 + 0.85 * sweep(1.0) + 0.15 * _smooth_signal(rng, times, T, 3, 3)))
    # Elevation biased upward: grazing views (where the board is unreadable) stay brief.
    e01 = np.clip(0.5 * (1 + 0.93 * sweep(1.4) + 0.07 * _smooth_signal(rng, times, T, 3, 2)), 0, 1)
    el = np.radians(e_lo + (e_hi - e_lo) * e01 ** 0.5)
    dist = d_lo + (d_hi - d_lo) * 0.5 * (1 + _smooth_signal(rng, times, T, 3, 1.3))
    roll = np.radians(cfg.roll_deg) * _smooth_signal(rng, times, T, 3, 4.0)
    jitter = 0.002 * np.stack([_smooth_signal(rng, times, 0.7, 3) for _ in range(3)], -1)
    look_jit = 0.012 * np.stack([_smooth_signal(rng, times, T, 2, 3) for _ in range(3)], -1)
    fwd, side = np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    poses = []
    for i in range(len(times)):
        dirn = np.cos(el[i]) * (np.cos(az[i]) * fwd + np.sin(az[i]) * side) + np.sin(el[i]) * UP
        eye = c_obj + dist[i] * dirn + jitter[i]
        c2w = look_at(eye, target0 + look_jit[i], UP)
        Rz, _ = cv2.Rodrigues(np.array([0.0, 0.0, roll[i]]))
        c2w[:3, :3] = c2w[:3, :3] @ Rz
        poses.append(c2w)
    return np.stack(poses)
