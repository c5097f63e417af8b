"""Camera intrinsics from board detections (OpenCV's calibration, or the precise variant)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Sequence

import cv2
import numpy as np

from ..capture.board import BoardSpec
from ..capture.footage import FootageSource, blurry_mask, to_gray8
from ..core.errors import DbbError
from ..geometry.cameras import Intrinsics
from ..geometry.transforms import c2w_from_rvec_tvec
from .corners import refine_xjunctions
from .detect import Detection, DetectorConfig, detect_sampled
from .solve import PoseConfig, corner_inliers, solve_pose


def refine_views(source: FootageSource, dets: Sequence[Detection], board: BoardSpec,
                 radius_max: float = 12.0) -> list[Detection]:
    """``dets`` with their corners re-fitted by :func:`refine_xjunctions` in full-resolution
    frames read again from ``source`` (the calibration views; detections of < 4 corners
    unchanged). Corners the fit cannot take (partly hidden, window off the image) are left
    out: calibration has corners to spare, and single bad corners pull the focal length.
    A larger window (``radius_max`` 20 px) cut the corner noise by 9% but bent the focal
    length on a barrel lens (+0.02 -> +0.04%): the straight-edge model meets curved edges."""
    by_index = {d.index: d for d in dets}
    out = {}
    for f in source.read(sorted(by_index), gray=True):
        d = by_index[f.index]
        if d.n_corners >= 4:
            corners, fitted = refine_xjunctions(to_gray8(f.image), board, d.ids, d.corners, radius_max)
            d = replace(d, ids=d.ids[fitted], corners=corners[fitted])
        out[d.index] = d
    return [out.get(d.index, d) for d in dets]


ALL_DIST_TERMS = "k1 k2 p1 p2 k3"   # OpenCV's five-term model (Calibration.dist_terms)


@dataclass(frozen=True)
class Calibration:
    """Intrinsics from board views: RMS reprojection error (px), views used and rejected (names),
    and the standard deviation (px) of fx and fy that the fit itself estimates (few or similar
    views leave the focal length loosely determined)."""

    intrinsics: Intrinsics
    rms: float
    used: tuple[str, ...]
    rejected: tuple[str, ...]
    fx_std: float = float("nan")
    fy_std: float = float("nan")
    square_pixels: bool = False   # fx = fy was imposed (the corners did not call for two)
    dist_terms: str = ALL_DIST_TERMS   # the distortion terms fitted (the others are 0)

    def to_json(self) -> dict:
        return {**self.intrinsics.to_json(), "rms": round(self.rms, 4),
                "fx_std": round(self.fx_std, 3), "fy_std": round(self.fy_std, 3),
                "square_pixels": self.square_pixels, "dist_terms": self.dist_terms,
                "views_used": len(self.used), "views_rejected": list(self.rejected)}


def _view_features(d: Detection, board: BoardSpec, width: int, height: int) -> np.ndarray:
    """A small vector describing how the board appears: position, size and perspective (homography)."""
    obj = board.chessboard_corners()[d.ids][:, :2]
    H, _ = cv2.findHomography(obj, d.corners)
    c = d.corners.mean(0)
    spread = np.log(d.corners.std(0).mean() / max(width, height) + 1e-6)
    if H is None:
        return np.array([c[0] / width, c[1] / height, spread, 0, 0])
    Hn = H / H[2, 2]
    persp = Hn[2, :2] * board.size_m[0] * 3  # foreshortening direction and strength
    return np.array([c[0] / width, c[1] / height, spread, persp[0], persp[1]])


def select_views(dets: Sequence[Detection], board: BoardSpec, width: int, height: int,
                 max_views: int = 40, min_corners: int = 8) -> list[Detection]:
    """Diverse board views for calibration: greedy farthest-point sampling over view features."""
    good = [d for d in dets if d.n_corners >= min_corners and
            not board.cv_board().checkCharucoCornersCollinear(d.ids)]
    if len(good) <= max_views:
        return good
    feats = np.stack([_view_features(d, board, width, height) for d in good])
    feats = (feats - feats.mean(0)) / (feats.std(0) + 1e-9)
    chosen = [int(np.argmax([d.n_corners for d in good]))]
    dist = np.linalg.norm(feats - feats[chosen[0]], axis=1)
    while len(chosen) < max_views:
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(feats - feats[k], axis=1))
    return [good[k] for k in sorted(chosen)]


def calibrate(dets: Sequence[Detection], board: BoardSpec, width: int, height: int,
              max_views: int = 40, min_views: int = 3, precise: bool = True) -> Calibration:
    """Intrinsics (OpenCV k1, k2, p1, p2, k3) from board detections, rejecting outlier views.

    Views whose own RMS exceeds max(3 x median, 1 px) are dropped and the fit repeated. With
    ``precise``, corners that disagree with their view's pose (see :func:`_corner_inliers`;
    beyond 4 x the capture's typical residual) are dropped, then views still over 3 x the
    median RMS, and the fit repeated; fx = fy is imposed unless the corners call for two
    focal lengths, and k3, p1, p2 are left at 0 unless they call for them. Without it, the fit is OpenCV's own (every corner of the kept views, free
    fx and fy), which is what OpenCV's calibration tools compute: from a few views the focal
    length is loose (+-3% from 4 photos) and either refinement alone moves it by 1-1.5 of its
    standard deviations, so only OpenCV's estimator reproduces OpenCV's figures there.
    """
    views = select_views(dets, board, width, height, max_views)
    if len(views) < min_views:
        raise DbbError(f"calibration needs at least {min_views} frames showing 8+ board corners, "
                       f"found {len(views)}")
    obj_all = board.chessboard_corners().astype(np.float32)
    rejected: list[str] = []
    flags = 0 if len(views) >= 4 else cv2.CALIB_FIX_K3
    for _ in range(3):
        objs = [obj_all[d.ids] for d in views]
        imgs = [d.corners.astype(np.float32) for d in views]
        rms, K, dist, rvecs, tvecs, std, _, per_view = cv2.calibrateCameraExtended(
            objs, imgs, (width, height), None, None, flags=flags)
        per_view = per_view.ravel()
        bad = per_view > max(3 * np.median(per_view), 1.0)
        if not bad.any() or len(views) - bad.sum() < min_views:
            break
        rejected += [d.name for d, b in zip(views, bad) if b]
        views = [d for d, b in zip(views, bad) if not b]
    std = np.ravel(std)
    if not precise:
        return Calibration(Intrinsics.from_matrix(width, height, K, dist), float(rms), tuple(d.name for d in views),
                           tuple(rejected), float(std[0]), float(std[1]))
    intr = Intrinsics.from_matrix(width, height, K, dist)
    # Partly hidden corners pull the focal length and principal point as they pull poses.
    # A corner is off beyond 4 x the capture's typical residual (not a fixed 0.25 px: the
    # re-fitted corners are good to ~0.02 px, so 0.1-0.25 px is already far off).
    res = [np.linalg.norm(cv2.projectPoints(o, r, t, K, dist)[0].reshape(-1, 2) - i, axis=1)
           for o, i, r, t in zip(objs, imgs, rvecs, tvecs)]
    cfg = PoseConfig(corner_floor_px=4 * float(np.median(np.concatenate(res))) / 1.1774)
    keep = [corner_inliers(o.astype(np.float64), i.astype(np.float64), c2w_from_rvec_tvec(r, t), intr, cfg)
            for o, i, r, t in zip(objs, imgs, rvecs, tvecs)]
    objs = [o if k is None else o[k] for o, k in zip(objs, keep)]
    imgs = [i if k is None else i[k] for i, k in zip(imgs, keep)]
    rms, K, dist, _, _, std, _, per_view = cv2.calibrateCameraExtended(
        objs, imgs, (width, height), K, dist, flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS)
    std = np.ravel(std)
    # Views still 3 x the typical RMS have more bad corners than may be dropped (half the
    # corners of a view behind the object, say): out, without the 1-px floor above.
    bad = np.ravel(per_view) > 3 * np.median(per_view)
    if bad.any() and len(objs) - bad.sum() >= min_views:
        rejected += [d.name for d, b in zip(views, bad) if b]
        views = [d for d, b in zip(views, bad) if not b]
        objs = [o for o, b in zip(objs, bad) if not b]
        imgs = [i for i, b in zip(imgs, bad) if not b]
        rms, K, dist, _, _, std, _, _ = cv2.calibrateCameraExtended(
            objs, imgs, (width, height), K, dist, flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS)
        std = np.ravel(std)
    fx_std, fy_std = float(std[0]), float(std[1])
    # Square pixels (fx = fy) unless the corners say otherwise (likelihood-ratio test, 1 dof,
    # p = 0.001): a free aspect ratio trades off against the principal point and leaves both
    # several times looser (e.g. cy +-2.9 px instead of +-1.6 from a 40-view sweep).
    K_sq = K.copy()
    K_sq[0, 0] = K_sq[1, 1] = 0.5 * (K[0, 0] + K[1, 1])
    sq = cv2.calibrateCameraExtended(objs, imgs, (width, height), K_sq, dist.copy(),
                                     flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO)
    n_points = sum(len(o) for o in objs)
    square = n_points * (sq[0] ** 2 - rms ** 2) / max(rms ** 2 / 2, 1e-12) < 10.83
    if square:
        rms, K, dist = sq[0], sq[1], sq[2]
        fx_std = fy_std = float(np.ravel(sq[5])[1])   # fy is the free one; fx follows it
    # Distortion terms the corners do not call for (the same test; 1-3 dof) stay at 0: a free
    # k3 or decentring (p1, p2) trades off against the principal point. Simplest model first.
    base = flags | cv2.CALIB_USE_INTRINSIC_GUESS | (cv2.CALIB_FIX_ASPECT_RATIO if square else 0)
    terms = ALL_DIST_TERMS if not flags & cv2.CALIB_FIX_K3 else "k1 k2 p1 p2"
    for extra, zero, crit, name in ((cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3, [2, 3, 4], 16.27, "k1 k2"),
                                    (cv2.CALIB_FIX_K3, [4], 10.83, "k1 k2 p1 p2"),
                                    (cv2.CALIB_ZERO_TANGENT_DIST, [2, 3], 13.82, "k1 k2 k3")):
        d0 = np.ravel(dist).copy()
        d0[zero] = 0.0
        red = cv2.calibrateCameraExtended(objs, imgs, (width, height), K.copy(), d0.reshape(1, -1), flags=base | extra)
        if n_points * (red[0] ** 2 - rms ** 2) / max(rms ** 2 / 2, 1e-12) < crit:
            rms, K, dist, terms = red[0], red[1], red[2], name
            std = np.ravel(red[5])
            fx_std, fy_std = (float(std[1]),) * 2 if square else (float(std[0]), float(std[1]))
            break
    return Calibration(Intrinsics.from_matrix(width, height, K, dist), float(rms), tuple(d.name for d in views),
                       tuple(rejected), fx_std, fy_std, bool(square), terms)


# Given intrinsics misfit the footage when their board reprojection error is this many times the
# one a quick calibration of the same views reaches, and this many px more (docs/commands/preprocess.md).
# Correct ones come within 1.05 x (synthetic footage with and without distortion, OpenCV's photos
# with its own calibration); a focal length 1.5 x wrong is 5-50 x at 320-640 px.
MISFIT_RATIO, MISFIT_PX = 3.0, 0.1


@dataclass(frozen=True)
class IntrinsicsFit:
    """How well given intrinsics fit board views: the RMS reprojection error (px) of the views'
    corners, each view posed under them (``given_rms``) and under a quick calibration of the
    same views (``calibrated_rms``, OpenCV's, five distortion terms), over ``views`` views."""

    given_rms: float
    calibrated_rms: float
    views: int

    @property
    def misfit(self) -> bool:
        """Far above what the views call for: :data:`MISFIT_RATIO` x and :data:`MISFIT_PX` more."""
        return self.given_rms > MISFIT_RATIO * self.calibrated_rms and self.given_rms - self.calibrated_rms > MISFIT_PX


def intrinsics_fit(dets: Sequence[Detection], board: BoardSpec, intr: Intrinsics, max_views: int = 12,
                   min_views: int = 4) -> IntrinsicsFit | None:
    """:class:`IntrinsicsFit` of ``intr`` over the ``max_views`` most diverse of ``dets`` (those
    OpenCV's calibration keeps); None when fewer than ``min_views`` show 8+ corners off a line."""
    views = select_views(dets, board, intr.width, intr.height, max_views)
    if len(views) < min_views:
        return None
    cal = calibrate(views, board, intr.width, intr.height, max_views, min_views, precise=False)
    obj_all = board.chessboard_corners()
    sq, n = 0.0, 0
    for d in views:
        sol = solve_pose(obj_all[d.ids], d.corners, intr) if d.name in cal.used else None
        if sol is not None:
            sq, n = sq + sol[1] ** 2 * d.n_corners, n + d.n_corners
    return IntrinsicsFit(float(np.sqrt(sq / n)), cal.rms, len(cal.used)) if n else None


def calibrate_footage(source: FootageSource, board: BoardSpec, fps: float | None = None,
                      max_views: int = 40, blur_ratio: float = 0.4, workers: int = 1,
                      tick: Callable[[int], None] | None = None,
                      total: Callable[[int], None] | None = None,
                      precise: bool = False) -> Calibration:
    """Intrinsics of the camera that filmed ``source`` (sharp frames only).

    By default OpenCV's calibration (``cornerSubPix`` corners, see :func:`calibrate`), so the
    result agrees with OpenCV's tools; ``precise``: saddle-point corners, off-pose corners
    dropped, square pixels, the chosen views' corners re-fitted by :func:`refine_xjunctions`
    and distortion terms the corners do not call for left out (docs/decisions.md, precise self-calibration).
    """
    dets = detect_sampled(source, board, fps, DetectorConfig(saddle=precise), workers, tick, total)
    blurry = blurry_mask(np.array([d.sharpness for d in dets]), blur_ratio)
    sharp = [d for d, b in zip(dets, blurry) if not b]
    if precise:
        return calibrate_precise(source, sharp, board, max_views)
    return calibrate(sharp, board, source.info.width, source.info.height, max_views, precise=False)


def calibrate_precise(source: FootageSource, dets: Sequence[Detection], board: BoardSpec,
                      max_views: int) -> Calibration:
    """:func:`calibrate` (precise) on the ``max_views`` most diverse of ``dets`` (sharp frames of
    ``source``), their corners re-fitted by :func:`refine_xjunctions` in the full frames."""
    w, h = source.info.width, source.info.height
    views = refine_views(source, select_views(dets, board, w, h, max_views), board)
    return calibrate(views, board, w, h, max_views=max_views)
