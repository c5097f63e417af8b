"""Posed image datasets as typed records: frames, the object's volume, the dataset.

Every :class:`Frame` holds its camera in the toolkit's own conventions (OpenCV camera-to-world,
OpenCV pixel centres); :mod:`.transforms` converts at the file boundary.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..geometry.cameras import Intrinsics
from ..geometry.viewpoint import Viewpoint


@dataclass(frozen=True)
class Frame:
    """One posed image: where its pixels are, how they were seen and from where."""

    name: str                     # file stem, used to name renders and to pick held-out views
    image_path: Path
    c2w: np.ndarray               # (4, 4) board/world-from-camera, OpenCV camera axes
    intr: Intrinsics
    split: str = "train"          # "train" or "test"
    mask_path: Path | None = None
    time: float | None = None
    # Preprocess crops only: the observed crop and the room predicted behind it (RGB images the
    # matte was cut from), so training can composite over the predicted room (:mod:`.fields`).
    observed_path: Path | None = None
    background_path: Path | None = None
    # Crops only (crops.json): the footage frame it was cut from, the camera's viewpoint from the
    # object centre, and whether the crop reaches past that frame's border (padded transparent).
    source_frame: int | None = None
    viewpoint: Viewpoint | None = None
    touches_border: bool | None = None


@dataclass(frozen=True)
class ObjectVolume:
    """The sphere that holds the object, in world units (metres for captures)."""

    center: tuple[float, float, float]
    radius: float
    estimated: bool = False       # True when guessed from the cameras, not read from a file

    def to_json(self) -> dict:
        return {"center": [float(c) for c in self.center], "radius": float(self.radius),
                "estimated": self.estimated}


@dataclass(frozen=True)
class PosedDataset:
    """Frames of one dataset file, plus the object volume when the dataset states it."""

    source: Path                  # the json file read
    kind: str                     # "crops", "transforms" or "blender"
    frames: list[Frame]
    rgba: bool                    # images carry an alpha channel (or a mask) to supervise
    volume: ObjectVolume | None = None
    extras: dict = field(default_factory=dict)

    def split(self, name: str) -> list[Frame]:
        return [f for f in self.frames if f.split == name]


def estimate_volume(frames: list[Frame], margin: float = 1.1) -> ObjectVolume:
    """Guess the object sphere from the cameras alone.

    Centre: the point nearest (least squares) to all optical axes. Radius: what the
    view's half field of view holds at the nearest camera, times ``margin``: an object
    seen whole in every view fits in every view's cone.
    """
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for f in frames:
        o, d = f.c2w[:3, 3], f.c2w[:3, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ o
    try:
        c = np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        raise InputError("cannot estimate the object centre: the cameras' axes are parallel") from None
    dist = min(float(np.linalg.norm(f.c2w[:3, 3] - c)) for f in frames)
    # The wider half-angle of each view: tightly framed objects (NeRF-synthetic) stay whole.
    half = min(max(math.atan2(f.intr.width / 2, f.intr.fx), math.atan2(f.intr.height / 2, f.intr.fy))
               for f in frames)
    r = margin * dist * math.sin(half)
    return ObjectVolume(tuple(float(v) for v in c), r, estimated=True)  # type: ignore[arg-type]


def holdout_every(frames: list[Frame], n: int) -> list[Frame]:
    """Mark every ``n``-th frame (0, n, 2n, ...) as ``test``; the rest ``train``."""
    if n <= 0:
        return frames
    return [replace(f, split="test" if i % n == 0 else "train") for i, f in enumerate(frames)]


def holdout_named(frames: list[Frame], names: set[str]) -> list[Frame]:
    """Mark frames whose name (file stem) is in ``names`` as ``test``; the rest ``train``."""
    return [replace(f, split="test" if f.name in names else "train") for f in frames]
