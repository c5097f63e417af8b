"""Every camera and pixel convention the toolkit meets, and the one place that converts them.

Inside the toolkit poses are OpenCV-style: camera +x right, +y down, looking along +z; pixel
centres at integer coordinates (the centre of the top-left pixel is (0, 0)). Outside:

- OpenGL / nerfstudio / instant-ngp / glTF camera axes: +x right, +y up, looking along -z
  (:func:`opengl_from_opencv`, :func:`opencv_from_opengl`);
- ARKit (Record3D exports) camera axes are OpenGL's (:func:`opencv_from_arkit`);
- transforms-style files (nerfstudio, instant-ngp: ``transforms.json``, ``crops.json``, cameras
  files) and COLMAP put the pixel origin at the image's top-left *corner*: the centre of the
  top-left pixel is (0.5, 0.5), a centred camera has ``cx = w / 2`` (:func:`corner_from_centre_px`,
  :func:`centre_from_corner_px`). ``camera.json`` keeps OpenCV's centres.

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


def corner_from_centre_px(x: float) -> float:
    """A pixel coordinate with OpenCV's origin (the top-left pixel's centre at 0) in the files' and
    COLMAP's (the top-left corner at 0, so that pixel's centre at 0.5)."""
    return float(x) + 0.5


def centre_from_corner_px(x: float) -> float:
    """The inverse of :func:`corner_from_centre_px`: a file's (or COLMAP's) pixel coordinate in OpenCV's."""
    return float(x) - 0.5
