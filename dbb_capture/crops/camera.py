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
from dataclasses import dataclass, replace

import cv2
import numpy as np

from ..geometry.cameras import Intrinsics
from ..geometry.transforms import invert_rigid, look_at
from ..core.errors import DbbError
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


def crop_camera(c2w: np.ndarray, src: Intrinsics, center: np.ndarray, radius: float, up: np.ndarray,
                size: int = 64, fill: float = 0.9) -> CropCamera:
    """The crop camera of a frame taken by ``c2w`` (4, 4, OpenCV) with intrinsics ``src``.

    ``center`` (3,), ``radius`` (m): the object's bounding sphere in the board frame; ``size``:
    crop side in pixels; ``fill``: fraction of the side the sphere's projected diameter takes.
    """
    eye = c2w[:3, 3]
    D = float(np.linalg.norm(eye - center))
    if D <= radius * 1.001:
        raise DbbError(f"camera is inside the object's bounding sphere (distance {D:.3f} m, radius {radius:.3f} m)")
    half_angle = math.asin(radius / D)
    f = fill * size / 2 / math.tan(half_angle)
    # The object's up must not be parallel to the viewing direction (a view from straight above).
    view = (center - eye) / D
    if abs(view @ up) > 0.9995:
        raise DbbError("camera looks straight down the up axis: the crop's up is undefined")
    crop_c2w = look_at(eye, center, up)
    c = (size - 1) / 2
    intr = Intrinsics(size, size, f, f, c, c)
    f_src = 0.5 * (src.fx + src.fy)
    return CropCamera(intr, crop_c2w, viewpoint(eye, center, up), window_px=size * f_src / f)


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
    at 640x480 (docs/benchmarks.md, issue 4, tenth session).
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


def split_by_time(times: np.ndarray, test_fraction: float = 0.2) -> np.ndarray:
    """Split labels (N,) of str: the last ``test_fraction`` of the capture's duration is ``test``."""
    times = np.asarray(times, float)
    if len(times) == 0:
        return np.array([], dtype=object)
    t_cut = times.min() + (1 - test_fraction) * (times.max() - times.min())
    return np.where(times > t_cut if test_fraction > 0 else np.zeros(len(times), bool), "test", "train")


def follows_previous(times: np.ndarray, max_gap_factor: float = 1.5) -> np.ndarray:
    """(N,) bool: frame i directly follows frame i-1 (a time step at most ``max_gap_factor`` times
    the median step; a frame skipped for blur or for no board is a gap). Frame 0 follows nothing."""
    times = np.asarray(times, float)
    out = np.zeros(len(times), bool)
    if len(times) > 1:
        step = np.diff(times)
        out[1:] = step <= max_gap_factor * float(np.median(step))
    return out


def sequence_windows(times: np.ndarray, splits: np.ndarray, length: int = 11,
                     max_gap_factor: float = 1.5, stride: int = 1) -> list[tuple[int, str]]:
    """Start indices of windows of ``length`` consecutive frames (1 context + length-1 predicted).

    A window never crosses a split boundary or a gap (a frame skipped for blur or for no board,
    seen as a time step over ``max_gap_factor`` times the median step). Returns [(start, split)].
    """
    times = np.asarray(times, float)
    n = len(times)
    if n < length:
        return []
    step = float(np.median(np.diff(times))) if n > 1 else 1.0
    broken = np.zeros(n, bool)  # broken[i]: frame i does not follow frame i-1
    broken[1:] = (np.diff(times) > max_gap_factor * step) | (splits[1:] != splits[:-1])
    out = []
    for s in range(0, n - length + 1, stride):
        if not broken[s + 1:s + length].any():
            out.append((s, str(splits[s])))
    return out


@dataclass(frozen=True)
class CropRecord:
    """One crop of the dataset: its image file, its camera, where it came from."""

    file_path: str            # relative to the dataset folder, e.g. "crops/00012.png"
    cam: CropCamera
    source_frame: int
    time: float
    split: str
    touches_border: bool = False
    mask_path: str | None = None
    # The observed crop (RGB) and the background predicted there (RGB), e.g.
    # "crops_observed/00012.png", "crops_background/00012.png": what the matte was cut from,
    # so training can composite over the predicted room instead of trusting the matte alone.
    observed_path: str | None = None
    background_path: str | None = None

    def to_json(self) -> dict:
        from ..geometry.conventions import opengl_from_opencv

        i = self.cam.intr
        d = {"file_path": self.file_path,
             "transform_matrix": opengl_from_opencv(self.cam.c2w).round(9).tolist(),
             "fl_x": i.fx, "fl_y": i.fy, "cx": i.cx, "cy": i.cy, "w": i.width, "h": i.height,
             "source_frame": self.source_frame, "time": round(self.time, 6),
             "viewpoint": self.cam.viewpoint.to_json(), "split": self.split,
             "touches_border": self.touches_border}
        if self.mask_path:
            d["mask_path"] = self.mask_path
        if self.observed_path and self.background_path:
            d["observed_path"] = self.observed_path
            d["background_path"] = self.background_path
        return d


def crops_json(records: list[CropRecord], center: np.ndarray, radius: float, up: np.ndarray,
               size: int, fill: float, sequence_length: int = 11) -> dict:
    """The ``crops.json`` document: nerfstudio schema with per-frame crop intrinsics.

    Top level also records the object sphere (board frame), the up direction, the crop size
    and fill, and the sequence windows (start frame indices of 1 context + N predicted).
    """
    times = np.array([r.time for r in records])
    splits = np.array([r.split for r in records])
    windows = sequence_windows(times, splits, sequence_length)
    return {"camera_model": "OPENCV", "w": size, "h": size,
            "k1": 0.0, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0,
            "object": {"center": [round(float(v), 6) for v in center], "radius": round(float(radius), 6)},
            "up": [float(v) for v in up], "crop_size": size, "crop_fill": fill,
            "sequence_length": sequence_length,
            "sequences": [{"start": s, "split": sp} for s, sp in windows],
            "frames": [r.to_json() for r in records]}


# --------------------------------------------------------------------------- one frame, end to end
@dataclass(frozen=True)
class ObjectCrop:
    """What one frame gives: the crop camera, the observed crop (S, S, 3), the predicted
    background there (S, S, 3) and the straight RGBA cut-out (S, S, 4), all uint8; for the
    matte's second pass also where the prediction is a guess (S, S) bool and, for a crop past
    the frame's border, the part inside the frame (S, S) uint8 (255: inside). S is the matte's
    size, ``scale`` times the output's (the camera matches S)."""

    cam: CropCamera
    observed: np.ndarray
    predicted: np.ndarray
    rgba: np.ndarray
    touches_border: bool
    guessed: np.ndarray | None = None
    inside: np.ndarray | None = None
    noise: float = float("nan")   # the matte's noise level in this crop (:func:`.matte.noise_level`)
    room_detail: float = float("nan")  # share of the room's detail the prediction keeps (:func:`.matte.room_detail`)
    scale: int = 1                # the arrays are at ``scale`` x the output size (the matte's; see :func:`at_output`)


def crop_windows(c2ws, src: Intrinsics, center: np.ndarray, radius: float, up: np.ndarray, size: int,
                 fill: float) -> np.ndarray:
    """:attr:`CropCamera.window_px` (N,) of the crop camera of every frame taken by ``c2ws`` (N of (4, 4))."""
    return np.array([crop_camera(c, src, center, radius, up, size, fill).window_px for c in c2ws])


def matte_scale(windows_px: np.ndarray, size: int, between: tuple[float, float]) -> int:
    """How many times the output size a capture's crops are matted at: 2 where the median crop
    window (``windows_px`` (N,): :attr:`CropCamera.window_px` of every frame) holds between
    ``between`` source pixels per crop pixel, else 1. One scale for the whole capture: the
    second pass compares neighbouring frames' alphas pixel by pixel.

    The matte decides per pixel and makes the outline fractional over a 1-px band; at twice the
    size both are half as coarse and averaging down gives the outline pixels their coverage
    (640x480 footage, 64 px crops: alpha IoU +0.01 to +0.03). It holds down to about one source
    pixel per crop pixel, where the doubled crop is upsampled footage: 128 px crops of 640x480
    (1.3 source px per crop px), cut with bicubic taps, gain +1.1 dB on white against the truth
    and the tree +0.3 dB (docs/benchmarks.md, issue 4, tenth session; with bilinear taps it had
    lost). Further below, the matte's pixel-sized steps would over-resolve the footage; above the
    range the 1x matte meets its bars and the 4x pixels (background render included) would cost
    the real-time throughput.
    """
    if not len(windows_px):
        return 1
    ratio = float(np.median(windows_px)) / size
    return 2 if between[0] <= ratio < between[1] else 1


def matte_config_at(cfg, scale: int):
    """The matte's settings (:class:`~dbb_capture.crops.matte.MatteConfig`) for a crop at ``scale`` x
    the output size: the fractional band at the outline stays one output pixel wide (at 2x with a
    2-px band, alpha IoU +0.004 to +0.011 over a 1-px band). The other pixel sizes stay as they
    are: the 1-px shift tolerance doubled lost 0.002-0.011."""
    return cfg if scale == 1 else replace(cfg, edge_px=cfg.edge_px * scale)


def _area_down(image: np.ndarray, size: int) -> np.ndarray:
    out = cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)
    return out.reshape(size, size, *image.shape[2:])


def premultiplied_down(rgba: np.ndarray, size: int) -> np.ndarray:
    """Straight RGBA (S', S', 4) uint8 averaged down to (size, size, 4): colour weighted by
    alpha (premultiplied), so the room's colour behind transparent pixels does not bleed in."""
    a = rgba[..., 3:].astype(np.float32) / 255.0
    pm = _area_down(np.concatenate([rgba[..., :3].astype(np.float32) * a, a], -1), size)
    cover = pm[..., 3:]
    colour = np.where(cover > 1e-3, pm[..., :3] / np.maximum(cover, 1e-3), 0.0)
    return np.round(np.concatenate([np.clip(colour, 0, 255), cover * 255], -1)).astype(np.uint8)


def at_output(oc: ObjectCrop) -> ObjectCrop:
    """``oc`` at its output size: the camera resized, the arrays averaged down (RGBA through
    :func:`premultiplied_down`, the frame coverage as area); the identity at scale 1. An empty
    ``rgba`` (a first-pass crop loaded without it) stays empty."""
    if oc.scale == 1:
        return oc
    size = oc.cam.intr.width // oc.scale
    rgba = premultiplied_down(oc.rgba, size) if oc.rgba.size else oc.rgba
    guessed = _area_down(oc.guessed.astype(np.uint8), size) > 0 if oc.guessed is not None else None
    inside = _area_down(oc.inside, size) if oc.inside is not None else None
    return replace(oc, cam=oc.cam.resized(size), observed=_area_down(oc.observed, size),
                   predicted=_area_down(oc.predicted, size), rgba=rgba, guessed=guessed, inside=inside, scale=1)


def object_crop(image: np.ndarray, src: Intrinsics, c2w: np.ndarray, center: np.ndarray, radius: float,
                up: np.ndarray, size: int, fill: float, predict, matte_cfg=None, guessed=None,
                scale: int = 1) -> ObjectCrop:
    """Crop, predict the background, matte: the per-frame work of preprocessing (pure function).

    ``image`` (H, W, 3) uint8 with intrinsics ``src`` (distortion allowed) and OpenCV ``c2w``;
    ``predict(cam) -> (S, S, 3) uint8`` renders the background model in a crop camera;
    ``guessed(cam) -> (S, S) bool`` (optional) marks where that prediction is only a guess.
    Pixels of the crop outside the frame are transparent (and the crop is flagged).

    The crop is matted at ``scale`` times ``size`` (:func:`matte_scale`) and returned at that
    scale, for the second pass; :func:`at_output` brings it to ``size``.
    """
    from .matte import MatteConfig, matte_and_noise, sphere_disc

    mcfg = matte_config_at(matte_cfg or MatteConfig(), scale)
    n = size * scale
    cam = crop_camera(c2w, src, center, radius, up, n, fill)
    observed, touched = cut_crop(image, cam, src, c2w)
    predicted = predict(cam)
    guess = guessed(cam) if guessed is not None else None
    rgba, noise, detail = matte_and_noise(observed, predicted, sphere_disc(n, fill, mcfg.disc_margin), mcfg, guess)
    inside = None
    if touched:
        inside = cut_crop(np.full(image.shape[:2], 255, np.uint8), cam, src, c2w)[0].reshape(n, n)
        rgba[..., 3] = np.minimum(rgba[..., 3], inside)
    return ObjectCrop(cam, observed, predicted, rgba, touched, guess, inside, noise, detail, scale)


def rematte(oc: ObjectCrop, fill: float, capture, matte_cfg=None) -> np.ndarray:
    """The matte's second pass over one crop: alpha (S, S) uint8 with the capture's statistics
    (``capture``: :class:`~dbb_capture.crops.matte.CaptureMatte`), clipped to the frame like the first."""
    from .matte import MatteConfig, matte, sphere_disc

    mcfg = matte_config_at(matte_cfg or MatteConfig(), oc.scale)
    disc = sphere_disc(oc.observed.shape[0], fill, mcfg.disc_margin)
    alpha = matte(oc.observed, oc.predicted, disc, mcfg, oc.guessed, capture)[..., 3]
    return np.minimum(alpha, oc.inside) if oc.inside is not None else alpha


def vote_neighbours(k: int, linked: np.ndarray) -> list[int]:
    """Positions whose alphas crop ``k`` of a run votes with: itself and the frames right before
    and after it where no gap lies between (``linked`` (N,) bool: :func:`follows_previous`)."""
    return [k] + ([k - 1] if k > 0 and linked[k] else []) + ([k + 1] if k + 1 < len(linked) and linked[k + 1] else [])


def voted_rgba(oc: ObjectCrop, alphas: list[np.ndarray]) -> np.ndarray:
    """Straight RGBA (S, S, 4) uint8 of ``oc`` with the temporal median of its own and its
    neighbouring frames' second-pass alphas (each (S, S) uint8)."""
    from .matte import straight_rgba, temporal_median

    alpha = temporal_median(alphas)
    if oc.inside is not None:
        alpha = np.minimum(alpha, oc.inside)
    return straight_rgba(oc.observed, oc.predicted, alpha.astype(np.float32) / 255.0)


def alpha_in_frame(alpha: np.ndarray, cam: CropCamera, intr: Intrinsics, c2w: np.ndarray) -> np.ndarray:
    """A crop's alpha (S, S) uint8 drawn back into a full undistorted frame (H, W) uint8.

    The crop camera shares the frame camera's centre, so the map is the homography
    ``K_frame R K_crop^-1`` (``R``: crop camera to frame camera rotation).
    """
    R = invert_rigid(c2w)[:3, :3] @ cam.c2w[:3, :3]
    H = intr.K @ R @ np.linalg.inv(cam.intr.K)
    return cv2.warpPerspective(alpha, H, (intr.width, intr.height), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def temporal_difference(prev: np.ndarray, cur: np.ndarray, gain: float = 4.0) -> np.ndarray:
    """The thesis's "dx" view (S, S, 3) uint8: |cur - prev| of premultiplied RGBA crops, amplified."""
    def pm(x):
        return x[..., :3].astype(np.float32) * (x[..., 3:4].astype(np.float32) / 255.0)
    return np.clip(np.abs(pm(cur) - pm(prev)) * gain, 0, 255).astype(np.uint8)


def on_checker(rgba: np.ndarray, cell: int = 8) -> np.ndarray:
    """Straight RGBA (H, W, 4) uint8 over a grey checkerboard, (H, W, 3) uint8, for viewing."""
    h, w = rgba.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    bg = np.where(((yy // cell + xx // cell) % 2)[..., None] == 0, 200, 150).astype(np.float32)
    a = rgba[..., 3:4].astype(np.float32) / 255.0
    return np.round(rgba[..., :3] * a + bg * (1 - a)).astype(np.uint8)
