"""The background field's training rays: each view's crop window, cut from the footage."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import torch

from ..core.errors import DbbError
from ..crops.camera import CropCamera, crop_camera, cut_crop
from ..geometry.cameras import Intrinsics
from .config import BackgroundConfig
from .field import flat_rays


@dataclass(frozen=True)
class TrainingView:
    """A source frame to learn from: RGB (H, W, 3) uint8, its (possibly distorted) camera, OpenCV c2w."""

    image: np.ndarray
    intr: Intrinsics
    c2w: np.ndarray


def view_rays(view: TrainingView, center: np.ndarray, radius: float, up: np.ndarray, size: int, fill: float,
              drop_sphere: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame's training rays: its crop window cut at ``size`` pixels (pure function).

    Returns origins, dirs (M, 3) float32 and colours (M, 3) float32 in 0..1; pixels outside the
    frame are left out, and with ``drop_sphere`` (a radius factor) so is every pixel whose ray
    passes within ``drop_sphere * radius`` of the centre (the object is in this frame).
    """
    cam = crop_camera(view.c2w, view.intr, center, radius, up, size, fill)
    rgb, touched = cut_crop(view.image, cam, view.intr, view.c2w)
    keep = np.ones(rgb.shape[0] * rgb.shape[1], bool)
    if touched:  # only then can pixels lie outside the frame
        mask, _ = cut_crop(np.full(view.image.shape[:2], 255, np.uint8), cam, view.intr, view.c2w)
        keep = mask.reshape(-1) == 255
    o, d = flat_rays(cam)
    if drop_sphere is not None:
        oc = center - o
        along = (oc * d).sum(1)
        miss2 = (oc * oc).sum(1) - along ** 2
        keep &= miss2 > (drop_sphere * radius) ** 2
    cols = rgb.reshape(-1, 3)[keep].astype(np.float32) / 255.0
    return o[keep].astype(np.float32), d[keep].astype(np.float32), cols


@dataclass
class RayBank:
    origins: torch.Tensor
    dirs: torch.Tensor
    rgb: torch.Tensor

    @property
    def n(self) -> int:
        return int(self.rgb.shape[0])


def build_bank(views: Iterable[TrainingView], center: np.ndarray, radius: float, up: np.ndarray,
               cfg: BackgroundConfig, drop_sphere: bool,
               tick: Callable[[], None] | None = None, allow_empty: bool = False) -> RayBank:
    parts = []
    for v in views:
        parts.append(view_rays(v, center, radius, up, cfg.train_size, cfg.train_fill,
                               cfg.sphere_margin if drop_sphere else None))
        if tick:
            tick()
    if not parts:
        if allow_empty:
            return RayBank(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, 3))
        raise DbbError("no posed frames to learn the background from")
    o, d, c = (torch.from_numpy(np.concatenate(x)) for x in zip(*parts))
    return RayBank(o, d, c)


def room_rays(cam: CropCamera, observed: np.ndarray, alpha: np.ndarray, inside: np.ndarray | None,
              grow_px: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A matted crop's room rays (pure function): origins, dirs (M, 3) float32 and colours (M, 3)
    float32 0..1 of the pixels of ``observed`` (S, S, 3) uint8 that ``alpha`` (S, S) uint8 calls
    room, at least ``grow_px`` pixels from anything it calls object, inside the frame (``inside``
    (S, S) uint8, 255 inside, or None)."""
    import cv2

    k = 2 * grow_px + 1
    room = cv2.dilate((alpha > 0).astype(np.uint8), np.ones((k, k), np.uint8)) == 0
    if inside is not None:
        room &= inside == 255
    keep = room.reshape(-1)
    o, d = flat_rays(cam)
    return (o[keep].astype(np.float32), d[keep].astype(np.float32),
            observed.reshape(-1, 3)[keep].astype(np.float32) / 255.0)
