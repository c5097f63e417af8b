"""Distance-normalized, upright, object-centred crops; each crop is its own pinhole camera.

A crop camera shares the real camera's centre but is rotated to look straight at the object
centre, with its image "up" along the scene's up (the board normal on the cameras' side), so
camera roll is cancelled. Its focal length makes the object's bounding sphere project to a
circle of the same size in every crop: for a sphere of radius r seen from distance D along the
optical axis the silhouette is a circle of radius f * tan(asin(r / D)) pixels, so

    f_crop = fill * size / 2 / tan(asin(r / D)).

In the source frame that window's side is therefore inversely proportional to the distance
(~ r / D), as the thesis asks (6.1.3). A rotation about the camera centre is a homography, so
the crop is exact for any scene; lens distortion is handled by projecting the crop's rays
through the source camera's distortion model, in one resampling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..core.errors import DbbError
from ..geometry.cameras import Intrinsics
from ..geometry.transforms import invert_rigid, look_at
from ..geometry.viewpoint import Viewpoint, viewpoint


@dataclass(frozen=True)
class CropCamera:
    """A crop's pinhole camera: intrinsics (no distortion) and OpenCV camera-to-world (4, 4)."""

    intr: Intrinsics
    c2w: np.ndarray
    viewpoint: Viewpoint
    window_px: float          # side of the crop window measured in source pixels (at the centre)

    def resized(self, size: int) -> "CropCamera":
        """The same view at ``size`` x ``size`` pixels (focal length scaled, centre at the middle)."""
        s = size / self.intr.width
        c = (size - 1) / 2
        return CropCamera(Intrinsics(size, size, self.intr.fx * s, self.intr.fy * s, c, c), self.c2w,
                          self.viewpoint, self.window_px)


def facing_camera(eye: np.ndarray, center: np.ndarray, radius: float, up: np.ndarray,
                  size: int, fill: float) -> tuple[np.ndarray, Intrinsics]:
    """The square pinhole camera at ``eye`` (3,) that looks at the object sphere (``center`` (3,),
    ``radius`` m) with image up toward ``up``, the sphere's silhouette filling ``fill`` of its
    ``size`` pixels: OpenCV camera-to-world (4, 4) and intrinsics (centred principal point).

    Its image covers, through the centre and square to the optical axis, a plane of side
    ``2 D tan(asin(r / D)) / fill`` (:func:`canvas_side`): the billboard's canvas.
    """
    eye = np.asarray(eye, float)
    D = float(np.linalg.norm(eye - center))
    if D <= radius * 1.001:
        raise DbbError(f"camera is inside the object's bounding sphere (distance {D:.3f} m, radius {radius:.3f} m)")
    f = fill * size / 2 / math.tan(math.asin(radius / D))
    # The object's up must not be parallel to the viewing direction (a view from straight above).
    if abs((center - eye) / D @ up) > 0.9995:
        raise DbbError("camera looks straight down the up axis: the crop's up is undefined")
    c = (size - 1) / 2
    return look_at(eye, center, up), Intrinsics(size, size, f, f, c, c)


def canvas_side(distance: float, radius: float, fill: float) -> float:
    """Side (m) of the plane through the object centre, square to the view, that a
    :func:`facing_camera` image covers from ``distance`` m."""
    return 2 * distance * math.tan(math.asin(radius / distance)) / fill


def crop_camera(c2w: np.ndarray, src: Intrinsics, center: np.ndarray, radius: float, up: np.ndarray,
                size: int = 64, fill: float = 0.9) -> CropCamera:
    """The crop camera of a frame taken by ``c2w`` (4, 4, OpenCV) with intrinsics ``src``.

    ``center`` (3,), ``radius`` (m): the object's bounding sphere in the board frame; ``size``:
    crop side in pixels; ``fill``: fraction of the side the sphere's projected diameter takes.
    """
    eye = c2w[:3, 3]
    crop_c2w, intr = facing_camera(eye, center, radius, up, size, fill)
    f_src = 0.5 * (src.fx + src.fy)
    return CropCamera(intr, crop_c2w, viewpoint(eye, center, up), window_px=size * f_src / intr.fx)


def _project_crop_points(cam: CropCamera, src: Intrinsics, R: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Source pixels (len(v), len(u), 2) of crop pixel positions on the grid ``u`` x ``v``."""
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([(uu - cam.intr.cx) / cam.intr.fx, (vv - cam.intr.cy) / cam.intr.fy, np.ones(uu.shape)], -1)
    d = rays.reshape(-1, 3) @ R.T
    behind = d[:, 2] <= 1e-9
    d[behind, 2] = 1e-9
    uv, _ = cv2.projectPoints(d.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), src.K, src.dist_array)
    uv = uv.reshape(-1, 2)
    uv[behind] = -1e6
    return uv.reshape(len(v), len(u), 2)


def crop_maps(cam: CropCamera, src: Intrinsics, src_c2w: np.ndarray, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Source-pixel coordinates (map_x, map_y), each (size*s, size*s) float32, for ``cv2.remap``.

    Each crop (sub)pixel's ray is turned into the source camera and projected through its lens
    model (distortion included). With supersampling, rays are projected once per crop pixel
    corner and the map is interpolated between them: the map is smooth (a rotation and the
    lens), and projecting every subsample of a large window costs most of a frame's time.
    """
    R = invert_rigid(src_c2w)[:3, :3] @ cam.c2w[:3, :3]     # crop camera -> source camera rotation
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    fu = (np.arange(cam.intr.width)[:, None] + off[None, :]).reshape(-1)
    fv = (np.arange(cam.intr.height)[:, None] + off[None, :]).reshape(-1)
    if s <= 2:
        uv = _project_crop_points(cam, src, R, fu, fv)
    else:
        nu = np.arange(-0.5, cam.intr.width, 1.0)
        nv = np.arange(-0.5, cam.intr.height, 1.0)
        coarse = _project_crop_points(cam, src, R, nu, nv).astype(np.float32)
        # Node k sits at crop coordinate k - 0.5: a fine sample at x is at node coordinate x + 0.5.
        gx, gy = np.meshgrid((fu + 0.5).astype(np.float32), (fv + 0.5).astype(np.float32))
        uv = cv2.remap(coarse, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        behind = cv2.remap((coarse[..., 0] < -1e5).astype(np.float32), gx, gy, cv2.INTER_LINEAR) > 0
        uv[behind] = -1e6                          # behind the camera stays off the image
    return uv[..., 0].astype(np.float32), uv[..., 1].astype(np.float32)


def cut_crop(image: np.ndarray, cam: CropCamera, src: Intrinsics, src_c2w: np.ndarray) -> tuple[np.ndarray, bool]:
    """Resample ``image`` (H, W, C) uint8 into the crop (size, size, C); also whether it touched the border.

    Pixels outside the source frame are zero (transparent for RGBA). When the crop shrinks the
    image, it is rendered at ``s`` samples per pixel and box-filtered, so it does not alias. The
    taps are bicubic: a bilinear tap blurs by ~0.4 source px, ~0.3 crop px where a crop pixel
    spans few source pixels (low-resolution footage); bicubic gave +0.4 dB on black and on white
    at 640x480 (docs/decisions.md, bicubic taps).
    """
    s = max(1, min(8, math.ceil(cam.window_px / cam.intr.width)))
    mx, my = crop_maps(cam, src, src_c2w, s)
    h, w = image.shape[:2]
    touched = bool((mx < -0.5).any() or (my < -0.5).any() or (mx > w - 0.5).any() or (my > h - 0.5).any())
    out = cv2.remap(image, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if s > 1:
        size = cam.intr.width
        out = cv2.resize(out, (size, size), interpolation=cv2.INTER_AREA)
    if out.ndim == 2 and image.ndim == 3:
        out = out[..., None]
    return out, touched


def crop_windows(c2ws, src: Intrinsics, center: np.ndarray, radius: float, up: np.ndarray,
                 fill: float) -> np.ndarray:
    """:attr:`CropCamera.window_px` (N,) of the crop camera of every frame taken by ``c2ws`` (N of (4, 4)):
    the window does not depend on the crop's size, so it can choose that size."""
    return np.array([crop_camera(c, src, center, radius, up, 64, fill).window_px for c in c2ws])   # any size


CROP_SIZE_STEP = 16     # crop sizes chosen from the footage are multiples of this
MIN_CROP_SIZE = 32


def crop_size_for(windows_px: np.ndarray, max_size: int) -> int:
    """The crop side (pixels) that keeps the footage's detail: the median crop window
    (``windows_px`` (N,), source pixels) rounded down to a multiple of :data:`CROP_SIZE_STEP`,
    within [:data:`MIN_CROP_SIZE`, ``max_size``]. A crop pixel then spans at least one source
    pixel, so the crops are matted at twice their size and averaged down
    (:func:`~dbb_capture.crops.object.matte_scale`): on 960x720 footage, 320 px crops matted at
    640 px score +1.4 dB on white in novel views over 336 px crops matted at their size
    (docs/decisions.md, crop size from the footage). Finer crops would only interpolate the
    footage; coarser ones throw its detail away."""
    if not len(windows_px):
        return max(MIN_CROP_SIZE, min(max_size, 64))
    size = CROP_SIZE_STEP * math.floor(float(np.median(windows_px)) / CROP_SIZE_STEP)
    return int(max(MIN_CROP_SIZE, min(max_size, size)))
