"""Pinhole cameras with OpenCV distortion (pixels in OpenCV's convention, see :mod:`.conventions`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from .transforms import invert_rigid

MAX_SIDE_PX = 100_000              # camera.json: an image side larger than this is no camera's
FOCAL_RANGE = (0.05, 50.0)         # camera.json: focal lengths in units of the image's longer side
PRINCIPAL_RANGE = (0.1, 0.9)       # camera.json: principal point in units of the image's width, height


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with OpenCV distortion (k1, k2, p1, p2, k3); pixels, OpenCV centres."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def dist_array(self) -> np.ndarray:
        """Distortion as the (5,) float array OpenCV expects."""
        d = np.zeros(5)
        d[: len(self.dist)] = self.dist
        return d

    @property
    def distorted(self) -> bool:
        return bool(np.any(np.abs(self.dist_array) > 0))

    def to_json(self) -> dict:
        """``camera.json`` form: width, height, fx, fy, cx, cy, dist [k1, k2, p1, p2, k3]."""
        d = asdict(self)
        d["dist"] = [float(v) for v in self.dist_array]
        return d

    @classmethod
    def from_json(cls, d: dict, source: str = "camera.json") -> "Intrinsics":
        """The intrinsics of ``camera.json`` content ``d``, each entry checked on its own: a
        size of whole pixels, focal lengths of a field of view between about 1 and 170 degrees
        (:data:`FOCAL_RANGE` times the longer side), the principal point inside the middle 80 %
        of the image (:data:`PRINCIPAL_RANGE`), at most 5 finite distortion terms."""
        from ..core.fields import entry, number, numbers

        w, h = (number(entry(d, k, source), k, source, low=1, high=MAX_SIDE_PX, integer=True, unit=" px")
                for k in ("width", "height"))
        side = max(w, h)
        fx, fy = (number(entry(d, k, source), k, source, low=FOCAL_RANGE[0] * side, high=FOCAL_RANGE[1] * side,
                         unit=" px") for k in ("fx", "fy"))
        cx, cy = (number(entry(d, k, source), k, source, low=PRINCIPAL_RANGE[0] * n, high=PRINCIPAL_RANGE[1] * n,
                         unit=" px") for k, n in (("cx", w), ("cy", h)))
        dist = numbers(entry(d, "dist", source, []), "dist", source, range(6), hint=" [k1, k2, p1, p2, k3]")
        return cls(int(w), int(h), fx, fy, cx, cy, tuple(dist))

    @classmethod
    def from_matrix(cls, width: int, height: int, K: np.ndarray, dist: np.ndarray) -> "Intrinsics":
        """From OpenCV's camera matrix ``K`` (3, 3) and distortion coefficients (at least 5 used)."""
        d = np.ravel(dist)
        return cls(width, height, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                   tuple(float(v) for v in d[:5]))

    @classmethod
    def load(cls, path: Path) -> "Intrinsics":
        from ..core.outputs import read_json

        return cls.from_json(read_json(path, "camera file"), str(path))

    def undistorted(self) -> "Intrinsics":
        """Same pinhole with no distortion (for undistorted images of the same size)."""
        return Intrinsics(self.width, self.height, self.fx, self.fy, self.cx, self.cy)


def project_points(points_world: np.ndarray, c2w: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Project board-frame points (..., 3) through an OpenCV c2w (4, 4) camera to pixels (..., 2)."""
    import cv2

    w2c = invert_rigid(c2w)
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    pts = np.asarray(points_world, np.float64).reshape(-1, 1, 3)
    uv, _ = cv2.projectPoints(pts, rvec, w2c[:3, 3], intr.K, intr.dist_array)
    return uv.reshape(*np.shape(points_world)[:-1], 2)


def scaled_intrinsics(intr: Intrinsics, downscale: float) -> Intrinsics:
    """Intrinsics of the image resized by 1/``downscale`` (pixel centres kept consistent)."""
    if downscale == 1:
        return intr
    w = max(1, int(round(intr.width / downscale)))
    h = max(1, int(round(intr.height / downscale)))
    sx, sy = w / intr.width, h / intr.height
    # OpenCV centres: pixel edge 0 sits at -0.5 in both images.
    return replace(intr, width=w, height=h, fx=intr.fx * sx, fy=intr.fy * sy,
                   cx=(intr.cx + 0.5) * sx - 0.5, cy=(intr.cy + 0.5) * sy - 0.5)
