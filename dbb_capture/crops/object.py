"""One frame's object crop end to end: crop, predicted room, matte (two passes), and views of it."""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from ..geometry.cameras import Intrinsics
from ..geometry.transforms import invert_rigid
from .camera import CropCamera, crop_camera, cut_crop


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
    and the tree +0.3 dB (docs/decisions.md, supersample_between; with bilinear taps it had
    lost). Further below, the matte's pixel-sized steps would over-resolve the footage; above the
    range the 1x matte meets its bars and the 4x pixels (background render included) would cost
    the real-time throughput.
    """
    if not len(windows_px):
        return 1
    ratio = float(np.median(windows_px)) / size
    return 2 if between[0] <= ratio < between[1] else 1


def matte_config_at(cfg, scale: int, cam: CropCamera):
    """The matte's settings (:class:`~dbb_capture.crops.matte.MatteConfig`) for a crop at ``scale`` x
    the output size, cut by ``cam`` (at that scale).

    The doubled crop is resampled footage: its outline is spread over about
    ``supersampled_spread`` source pixels, and averaging down would spread it again. So the
    fractional band reaches that far to each side of the decided outline (at least one output
    pixel, as at 1x) and its alpha is steepened by ``supersampled_ramp``: the 2x outline is nearly
    sharp at the half-coverage line and averaging down alone makes the output's fractional
    pixels. Against the truth on white (first-pass crops): a 960x720 capture's 320 px crops, one
    source px a crop px (a 4-px band at 2x), 29.47 to 30.95 dB, the band without the ramp 30.38;
    64 px crops at 1.7-3.2 source px a crop px (a 2-px band) +0.15 to +0.42 dB, where a 3-px band
    lost 0.7-1.0 (docs/decisions.md, supersampled matte outline). The other pixel sizes stay as
    they are: the 1-px shift tolerance doubled lost 0.002-0.011 alpha IoU.
    """
    if scale == 1:
        return cfg
    band = max(cfg.edge_px * scale, round(cfg.supersampled_spread * cam.intr.width / cam.window_px))
    return replace(cfg, edge_px=band, edge_ramp=cfg.supersampled_ramp)


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

    n = size * scale
    cam = crop_camera(c2w, src, center, radius, up, n, fill)
    mcfg = matte_config_at(matte_cfg or MatteConfig(), scale, cam)
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

    mcfg = matte_config_at(matte_cfg or MatteConfig(), oc.scale, oc.cam)
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
