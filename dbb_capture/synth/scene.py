"""Synthetic captures with ground truth: a ChArUco board on a table in a textured room, a toy
object beside it, seen by a smooth handheld-like camera.

Everything is analytic ray casting, vectorized in PyTorch (2x2 or more stratified samples per
pixel): axis-aligned room box, table top and board on the plane z = 0, and the object as a set
of ellipsoids grouped into rigid parts. Parts of a dynamic object rotate about pivots:
arms swing periodically, the head wanders along a quasi-periodic (never repeating) path.

World frame = board frame (OpenCV ChArUco convention): the board lies face up on the table
in the plane z = 0, so "up" (toward the cameras) is -z and the table is at z >= 0 below.

The object's model (``ground_truth/object_model.json``) can be rendered alone as straight
RGBA for any camera and time with :func:`render_object_rgba`: that is the ground truth used
to score novel views.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from ..capture.board import BoardSpec
from ..geometry.cameras import Intrinsics
from .objects import ObjectModel, make_object


@dataclass(frozen=True)
class SynthConfig:
    """What to render. Lengths in metres, angles in degrees, times in seconds."""

    kind: str = "static"                     # "static" | "dynamic"
    seconds: float = 10.0
    fps: float = 10.0
    width: int = 640
    height: int = 480
    hfov_deg: float = 62.0
    seed: int = 0
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    board: BoardSpec = field(default_factory=lambda: BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100"))
    samples: int = 2                         # per pixel along each axis
    noise: float = 0.01                      # read-noise std, fraction of full scale
    background_seconds: float | None = 10.0  # clean plate length; None: no clean plate
    azimuth_range_deg: tuple[float, float] = (-60.0, 60.0)
    elevation_range_deg: tuple[float, float] = (10.0, 75.0)
    distance_range_m: tuple[float, float] = (0.5, 0.85)
    roll_deg: float = 4.0
    crf: int = 18                            # H.264 quality (lower: better, larger)
    workers: int = 0                         # render processes (0: 2 on multi-core machines for long captures)

    def intrinsics(self) -> Intrinsics:
        f = 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2)
        return Intrinsics(self.width, self.height, f, f, (self.width - 1) / 2 + 0.37,
                          (self.height - 1) / 2 - 0.61, tuple(float(v) for v in self.dist))


@dataclass
class Scene:
    """Everything the renderer needs that does not change from frame to frame."""

    board: BoardSpec
    obj: ObjectModel | None
    obj_sphere: tuple[np.ndarray, float]
    textures: dict[str, torch.Tensor]        # name -> (1, 3, H, W) float
    board_tex: torch.Tensor                  # (1, 1, H, W) float 0..1
    room_min: np.ndarray = field(default_factory=lambda: np.array([-2.2, -2.6, -2.4]))
    room_max: np.ndarray = field(default_factory=lambda: np.array([2.8, 2.4, 0.76]))
    table_min: np.ndarray = field(default_factory=lambda: np.array([-0.45, -0.45]))
    table_max: np.ndarray = field(default_factory=lambda: np.array([0.95, 0.75]))
    light: np.ndarray = field(default_factory=lambda: np.array([0.35, -0.6, -1.6]))

    def without_object(self) -> "Scene":
        return Scene(self.board, None, self.obj_sphere, self.textures, self.board_tex,
                     self.room_min, self.room_max, self.table_min, self.table_max, self.light)


def _noise_texture(rng: np.random.Generator, size: int, octaves: int = 5) -> np.ndarray:
    """Smooth value noise (size, size) in 0..1, tileable, from summed upsampled random grids."""
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = 4 * 2 ** o
        g = rng.random((n, n)).astype(np.float32)
        g = np.tile(g, (3, 3))  # tile so the cubic resize wraps around seamlessly
        big = cv2.resize(g, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)[size:2 * size, size:2 * size]
        out += amp * big
        total += amp
        amp *= 0.55
    out /= total
    return np.clip((out - out.min()) / (np.ptp(out) + 1e-6), 0, 1)


def make_textures(rng: np.random.Generator, size: int = 512) -> dict[str, torch.Tensor]:
    """Table (wood), floor (tiles), walls (patterned paper), ceiling: (1, 3, size, size) each."""
    u = np.linspace(0, 1, size, endpoint=False, dtype=np.float32)
    uu, vv = np.meshgrid(u, u)

    def rgb(base, img):
        return np.clip(np.asarray(base, np.float32)[None, None, :] * img[..., None], 0, 1)

    n1, n2, n3 = (_noise_texture(rng, size) for _ in range(3))
    wood = 0.75 + 0.25 * np.sin(2 * np.pi * (vv * 9 + 1.5 * n1))
    table = rgb(rng.uniform([0.55, 0.35, 0.2], [0.7, 0.5, 0.3]), wood * (0.85 + 0.3 * n2))
    tiles = ((np.floor(uu * 4) + np.floor(vv * 4)) % 2) * 0.25 + 0.6
    grout = ((np.abs((uu * 4) % 1 - 0.5) > 0.47) | (np.abs((vv * 4) % 1 - 0.5) > 0.47))
    floor = rgb(rng.uniform([0.5, 0.5, 0.5], [0.8, 0.75, 0.7]), np.where(grout, 0.3, tiles * (0.8 + 0.4 * n3)))
    motif = 0.8 + 0.2 * np.sin(2 * np.pi * 6 * uu) * np.sin(2 * np.pi * 6 * vv)
    wall = rgb(rng.uniform([0.6, 0.6, 0.55], [0.9, 0.85, 0.8]), motif * (0.75 + 0.4 * n1.T))
    ceiling = rgb([0.9, 0.9, 0.88], 0.85 + 0.15 * n2.T)
    return {k: torch.from_numpy(v).permute(2, 0, 1)[None].contiguous()
            for k, v in dict(table=table, floor=floor, wall=wall, ceiling=ceiling).items()}


def make_scene(cfg: SynthConfig, rng: np.random.Generator) -> Scene:
    obj = make_object(cfg.kind, cfg.board, rng)
    times = np.linspace(0, max(cfg.seconds, 60.0), 600) if obj.motions else np.zeros(1)
    sphere = obj.bounding_sphere(times)
    board_img = cfg.board.render(px_per_square=160).astype(np.float32) / 255.0
    # Printed paper is not pure black and white.
    board_img = 0.08 + 0.84 * board_img
    return Scene(cfg.board, obj, (sphere[0], sphere[1] * 1.03), make_textures(rng),
                 torch.from_numpy(board_img)[None, None])
