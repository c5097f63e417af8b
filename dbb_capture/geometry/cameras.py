"""Camera models and the one place that converts between camera conventions.

Inside the toolkit every pose is OpenCV-style: camera +x right, +y down, looking along +z,
pixel centres at integer coordinates (top-left pixel centre is (0, 0)). Files in the
nerfstudio/instant-ngp family store camera-to-world matrices in the OpenGL convention
(+x right, +y up, looking along -z); :func:`opengl_from_opencv` and
:func:`opencv_from_opengl` are the only conversions between the two.

Naming: ``board_from_camera`` maps camera coordinates to board (world) coordinates, i.e.
a camera-to-world matrix ``c2w``; ``camera_from_board`` is its inverse ``w2c``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import DbbError

# Flips camera y and z: OpenCV camera axes <-> OpenGL camera axes (an involution).
_FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_from_opencv(c2w: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (..., 4, 4) -> OpenGL/nerfstudio camera-to-world (..., 4, 4)."""
    return np.asarray(c2w, dtype=np.float64) @ _FLIP_YZ


def opencv_from_opengl(c2w: np.ndarray) -> np.ndarray:
    """OpenGL/nerfstudio camera-to-world (..., 4, 4) -> OpenCV camera-to-world (..., 4, 4)."""
    return np.asarray(c2w, dtype=np.float64) @ _FLIP_YZ


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
        try:
            dist = tuple(float(v) for v in d.get("dist", [0.0] * 5))
            return cls(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]),
                       float(d["cx"]), float(d["cy"]), dist)
        except (KeyError, TypeError, ValueError) as e:
            raise DbbError(f"{source}: missing or invalid intrinsics field ({e})") from None

    @classmethod
    def load(cls, path: Path) -> "Intrinsics":
        from ..core.outputs import read_json

        return cls.from_json(read_json(path, "camera file"), str(path))

    def nerfstudio_fields(self) -> dict:
        """The intrinsics keys of a nerfstudio ``transforms.json`` (OPENCV camera model)."""
        k1, k2, p1, p2, k3 = (float(v) for v in self.dist_array)
        return {"camera_model": "OPENCV", "fl_x": self.fx, "fl_y": self.fy, "cx": self.cx,
                "cy": self.cy, "w": self.width, "h": self.height,
                "k1": k1, "k2": k2, "k3": k3, "p1": p1, "p2": p2}

    def undistorted(self) -> "Intrinsics":
        """Same pinhole with no distortion (for undistorted images of the same size)."""
        return Intrinsics(self.width, self.height, self.fx, self.fy, self.cx, self.cy)


def pixel_grid(width: int, height: int, samples: int = 1) -> np.ndarray:
    """Pixel sample positions (height*s, width*s, 2) in OpenCV pixels, s x s stratified per pixel."""
    s = samples
    off = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(width)[:, None] + off[None, :]).reshape(-1)
    v = (np.arange(height)[:, None] + off[None, :]).reshape(-1)
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv], axis=-1)


def camera_rays(intr: Intrinsics, pixels: np.ndarray) -> np.ndarray:
    """Unit ray directions in the OpenCV camera frame (..., 3) for pixel positions (..., 2).

    Lens distortion is inverted with OpenCV's iterative undistortion (tight criteria), so a
    renderer using these rays agrees with ``cv2.projectPoints`` to well under 0.01 px.
    """
    import cv2

    pts = np.asarray(pixels, np.float64).reshape(-1, 1, 2)
    if intr.distorted:
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        # OpenCV 5 folded undistortPointsIter into undistortPoints (criteria argument).
        xy = cv2.undistortPoints(pts, intr.K, intr.dist_array, None, None, None, crit).reshape(-1, 2)
    else:
        xy = np.stack([(pts[:, 0, 0] - intr.cx) / intr.fx, (pts[:, 0, 1] - intr.cy) / intr.fy], -1)
    d = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d.reshape(*np.shape(pixels)[:-1], 3)


def project_points(points_world: np.ndarray, c2w: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Project board-frame points (..., 3) through an OpenCV c2w (4, 4) camera to pixels (..., 2)."""
    import cv2

    w2c = invert_rigid(c2w)
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    pts = np.asarray(points_world, np.float64).reshape(-1, 1, 3)
    uv, _ = cv2.projectPoints(pts, rvec, w2c[:3, 3], intr.K, intr.dist_array)
    return uv.reshape(*np.shape(points_world)[:-1], 2)
