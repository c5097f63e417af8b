"""Every camera and pixel convention the toolkit meets, and the one place that converts them.

Inside the toolkit poses are OpenCV-style: camera +x right, +y down, looking along +z; pixel
centres at integer coordinates (the centre of the top-left pixel is (0, 0)). Outside:

- OpenGL / nerfstudio / instant-ngp / glTF camera axes: +x right, +y up, looking along -z
  (:func:`opengl_from_opencv`, :func:`opencv_from_opengl`);
- ARKit (Record3D exports) camera axes are OpenGL's (:func:`opencv_from_arkit`);
- COLMAP's pixel origin is the top-left *corner*: the centre of the top-left pixel is
  (0.5, 0.5) (:func:`colmap_from_opencv_px`).

Naming: ``board_from_camera`` maps camera coordinates to board (world) coordinates, i.e. a
camera-to-world matrix ``c2w``; ``camera_from_board`` is its inverse ``w2c``.
"""

from __future__ import annotations

import numpy as np

# Flips camera y and z: OpenCV camera axes <-> OpenGL camera axes (an involution).
_FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_from_opencv(c2w: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (..., 4, 4) -> OpenGL/nerfstudio camera-to-world (..., 4, 4)."""
    return np.asarray(c2w, dtype=np.float64) @ _FLIP_YZ


def opencv_from_opengl(c2w: np.ndarray) -> np.ndarray:
    """OpenGL/nerfstudio camera-to-world (..., 4, 4) -> OpenCV camera-to-world (..., 4, 4)."""
    return np.asarray(c2w, dtype=np.float64) @ _FLIP_YZ


def opencv_from_arkit(c2w: np.ndarray) -> np.ndarray:
    """ARKit camera-to-world (..., 4, 4) (OpenGL camera axes, ARKit's world) -> OpenCV axes."""
    return opencv_from_opengl(c2w)


def colmap_from_opencv_px(x: float) -> float:
    """A pixel coordinate with OpenCV's origin (top-left pixel centre at 0) in COLMAP's (at 0.5)."""
    return float(x) + 0.5
