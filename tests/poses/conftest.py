"""A rendered sweep of board views with their true poses, and small pose sequences."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dbb_capture.capture.board import BoardSpec
from dbb_capture.geometry.transforms import look_at
from dbb_capture.poses.solve import FramePose
from dbb_capture.synth.render import Renderer, sensor
from dbb_capture.synth.scene import SynthConfig, make_scene

BOARD = BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100")


UP = np.array([0.0, 0.0, -1.0])


# (azimuth, elevation, distance): a sweep of angles and distances around the board centre.
VIEWS = [(0, 70, 0.45), (35, 50, 0.55), (-50, 40, 0.6), (15, 30, 0.5)]


def view_c2w(az: float, el: float, d: float, target: np.ndarray) -> np.ndarray:
    a, e = math.radians(az), math.radians(el)
    eye = target + d * np.array([math.sin(a) * math.cos(e), -math.cos(a) * math.cos(e), -math.sin(e)])
    return look_at(eye, target, UP)


@pytest.fixture(scope="module")
def rendered():
    """Board views (480x360, lens distortion, sensor noise) with their true poses and intrinsics."""
    cfg = SynthConfig(width=480, height=360, board=BOARD, dist=(-0.12, 0.05, 0.001, -0.001, 0.0))
    rng = np.random.default_rng(0)
    scene = make_scene(cfg, rng)
    intr = cfg.intrinsics()
    r = Renderer(intr, 2)
    views = []
    for az, el, d in VIEWS:
        c2w = view_c2w(az, el, d, BOARD.center)
        img, _ = r.render(scene, c2w, 0.0)
        views.append((c2w, cv2.cvtColor(sensor(img, 0.01, rng), cv2.COLOR_RGB2GRAY)))
    return intr, views


def smooth_path(n: int = 12) -> list[FramePose]:
    poses = []
    for i in range(n):
        c2w = view_c2w(-40 + 8 * i, 50, 0.6, BOARD.center)
        poses.append(FramePose(i, i / 10, f"{i:05d}", "posed", c2w, 20, 0.2, 0.1, c2w))
    return poses


def x_junction(centre: tuple[float, float], angles_deg: tuple[float, float], size: int = 41,
                blur: float = 1.2, noise: float = 1.0, seed: int = 0) -> np.ndarray:
    """A chessboard corner at sub-pixel ``centre``: two straight edges through it at the given
    angles (perspective skews them), 8x supersampled, blurred, noisy, uint8 (size, size)."""
    s = 8
    yy, xx = (np.mgrid[0:size * s, 0:size * s] + 0.5) / s - 0.5
    a, b = (np.radians(v) for v in angles_deg)
    # Share of each sub-sample on the positive side of each edge (no 1/8 px quantization).
    side_a = np.clip(0.5 + s * ((xx - centre[0]) * math.sin(a) - (yy - centre[1]) * math.cos(a)), 0, 1)
    side_b = np.clip(0.5 + s * ((xx - centre[0]) * math.sin(b) - (yy - centre[1]) * math.cos(b)), 0, 1)
    white = side_a * (1 - side_b) + side_b * (1 - side_a)
    img = (30.0 + 170.0 * white).reshape(size, s, size, s).mean(axis=(1, 3))
    img = cv2.GaussianBlur(img, (0, 0), blur)
    return np.clip(img + np.random.default_rng(seed).normal(0, noise, img.shape), 0, 255).astype(np.uint8)
