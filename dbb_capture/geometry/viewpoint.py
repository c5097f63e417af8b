"""Where a camera stands relative to an object: azimuth, elevation and distance about the scene's up."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.errors import DbbError


@dataclass(frozen=True)
class Viewpoint:
    """Where the camera stands relative to the object centre (degrees, metres).

    Elevation is measured from the board plane toward ``up``; azimuth is right-handed about
    ``up`` from the board's x axis (counter-clockwise seen from above: toward -y when up is -z).
    """

    azimuth_deg: float
    elevation_deg: float
    distance_m: float

    def to_json(self) -> dict:
        return {"azimuth_deg": round(self.azimuth_deg, 4), "elevation_deg": round(self.elevation_deg, 4),
                "distance_m": round(self.distance_m, 6)}

    def unit_vector(self) -> np.ndarray:
        """Direction from the object to the camera in the (x_ref, y_ref, up) frame, (3,)."""
        a, e = math.radians(self.azimuth_deg), math.radians(self.elevation_deg)
        return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def up_from_cameras(c2w: np.ndarray) -> np.ndarray:
    """The board normal on the side where the cameras are: -z or +z of the board frame (3,).

    ``c2w``: OpenCV camera-to-world poses (N, 4, 4) in the board frame. Derived from the data:
    most camera centres lie on one side of the board plane z = 0.
    """
    z = np.asarray(c2w)[:, 2, 3]
    if len(z) == 0:
        raise DbbError("no posed cameras to tell which side of the board is up")
    return np.array([0.0, 0.0, -1.0 if np.median(z) < 0 else 1.0])


def viewpoint(eye: np.ndarray, center: np.ndarray, up: np.ndarray) -> Viewpoint:
    """Azimuth, elevation and distance of a camera centre ``eye`` (3,) from ``center`` (3,)."""
    v = np.asarray(eye, float) - np.asarray(center, float)
    dist = float(np.linalg.norm(v))
    x_ref = np.array([1.0, 0.0, 0.0])
    y_ref = np.cross(up, x_ref)  # right-handed about up
    el = math.degrees(math.asin(np.clip(v @ up / dist, -1, 1)))
    az = math.degrees(math.atan2(v @ y_ref, v @ x_ref))
    return Viewpoint(az, el, dist)


def eye_at(vp: Viewpoint, center: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The camera centre (3,) standing at ``vp`` from ``center`` (3,): the inverse of :func:`viewpoint`."""
    up = np.asarray(up, float)
    x_ref = np.array([1.0, 0.0, 0.0])
    u = vp.unit_vector()
    return np.asarray(center, float) + vp.distance_m * (u[0] * x_ref + u[1] * np.cross(up, x_ref) + u[2] * up)
