"""ChArUco detection, camera calibration and per-frame camera poses in the board frame.

Flow: frames -> :class:`Detection` (board corners, full-resolution pixels) -> intrinsics
(given, or :func:`calibrate` from the detections) -> :class:`FramePose` per frame
(IPPE -> LM refinement, flip check, corner and reprojection gates) -> outlier rejection
along the video -> optional joint refinement of intrinsics and all poses.

Fast detection (:class:`BoardDetector`): markers are found on a reduced image, inside the
board's region from the previous frame when there is one, and the ChArUco corners are then
refined at full resolution. :func:`detect_footage` splits the footage into contiguous
segments decoded and detected in ``spawn`` worker processes (rawpy's OpenMP threads
deadlock under ``fork``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Callable, Sequence

import cv2
import numpy as np
from scipy.special import erf

from ..capture.board import BoardSpec
from ..geometry.cameras import Intrinsics, invert_rigid, rigid
from ..core.errors import DbbError
from ..capture.footage import FootageSource, blurry_mask, prefetched, sharpness, to_gray8
from ..core.parallel import map_spawned, report, split


# --------------------------------------------------------------------------- detection
@dataclass(frozen=True)
class Detection:
    """Board corners found in one frame. ``ids`` (N,) ChArUco ids, ``corners`` (N, 2) full-res px."""

    index: int
    time: float
    name: str
    ids: np.ndarray
    corners: np.ndarray
    n_markers: int
    sharpness: float

    @property
    def n_corners(self) -> int:
        return int(len(self.ids))


@dataclass(frozen=True)
class DetectorConfig:
    """Fast-path knobs. ``max_side``: long side (px) of the image markers are searched in."""

    max_side: int = 960
    track: bool = True
    refine: bool = True       # re-refine corners at full resolution (cornerSubPix)
    win_frac: float = 0.5     # refinement half-window, as a fraction of the square's white margin
    win_max: int = 6
    px_per_bit: float = 3.5   # reduce no further than this many px per marker bit (25th pct. marker)
    one_threshold: bool = True  # once marker size is known, one adaptive-threshold window, not 3
    saddle: bool = True       # final corners: saddle points of the image (:func:`refine_saddles`)
    saddle_frac: float = 0.8  # saddle-fit half-window, as a fraction of the square's white margin
    saddle_max: int = 8
    saddle_blur: float = 1.0  # Gaussian sigma (px) applied to the fitted patch
    xjunction_below: float = 6.0  # re-fit corners as X-junctions where white margins are under this (px)
    upsample_below: float = 2.0  # markers missed and the found ones under this many px per bit:
    upsample: tuple[float, ...] = (2.0, 3.0)  # ... search the board's region enlarged by these


_SCALES = (1.0, 2.0 / 3.0, 0.5, 1.0 / 3.0, 0.25)  # cheap resize factors


def _quantize_scale(scale: float, up: bool) -> float:
    """The nearest cheap resize factor at or above (``up``) or at or below ``scale``."""
    if up:
        return min(s for s in _SCALES if s >= scale - 1e-9) if scale <= 1 else 1.0
    return max([s for s in _SCALES if s <= scale + 1e-9] or [_SCALES[-1]])


class BoardDetector:
    """Stateful per-stream detector: remembers the board's region to search the next frame."""

    def __init__(self, board: BoardSpec, cfg: DetectorConfig = DetectorConfig()):
        self.board = board
        self.cfg = cfg
        self._cv_board = board.cv_board()
        self._det = cv2.aruco.CharucoDetector(self._cv_board)
        self._dets_by_window: dict[int, object] = {}
        self._window: int | None = None  # adaptive-threshold window for the next frame (px)
        self._roi: tuple[int, int, int, int] | None = None   # x0, y0, x1, y1 in full-res px
        self._last_n = 0
        self._scale_hint: float | None = None  # scale that keeps the last frame's markers readable

    def reset(self) -> None:
        self._roi, self._last_n, self._scale_hint, self._window = None, 0, None, None

    def _detector(self, window: int | None):
        """OpenCV's detector; with ``window``, thresholding at that one window size only
        (OpenCV's default tries 3, 13 and 23 px, which triples the marker search)."""
        if window is None or not self.cfg.one_threshold:
            return self._det
        if window not in self._dets_by_window:
            p = cv2.aruco.DetectorParameters()
            p.adaptiveThreshWinSizeMin = p.adaptiveThreshWinSizeMax = window
            self._dets_by_window[window] = cv2.aruco.CharucoDetector(
                self._cv_board, cv2.aruco.CharucoParameters(), p)
        return self._dets_by_window[window]

    def _detect_in(self, gray: np.ndarray, roi: tuple[int, int, int, int] | None, scale: float,
                   window: int | None = None):
        """detectBoard on ``gray`` cropped to ``roi`` and resized by ``scale``; results in full-res px."""
        x0, y0 = (roi[0], roi[1]) if roi else (0, 0)
        sub = gray[roi[1]:roi[3], roi[0]:roi[2]] if roi else gray
        # INTER_AREA is fast at 1/k (integer k); 2/3 goes through bilinear, which aliases a
        # little, harmless for finding markers (corners are refined at full resolution).
        integer = abs(1.0 / scale - round(1.0 / scale)) < 1e-6
        interp = cv2.INTER_CUBIC if scale > 1.0 else cv2.INTER_AREA if integer else cv2.INTER_LINEAR
        small = sub if scale == 1.0 else cv2.resize(sub, None, fx=scale, fy=scale, interpolation=interp)
        cc, ci, mc, mi = self._detector(window).detectBoard(small)
        n_markers = 0 if mi is None else int(len(np.ravel(mi)))
        if cc is None or ci is None or len(np.ravel(ci)) == 0:
            return None, None, n_markers, mc
        off = np.array([x0, y0], np.float64)
        # Pixel centres sit at integers in both images: full = (small + 0.5) / s - 0.5.
        corners = (np.asarray(cc, np.float64).reshape(-1, 2) + 0.5) / scale - 0.5 + off
        mcs = [(np.asarray(m, np.float64).reshape(-1, 2) + 0.5) / scale - 0.5 + off for m in mc]
        return np.asarray(ci).reshape(-1).astype(np.int32), corners, n_markers, mcs

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Board corners in a grey frame (H, W) uint8: (ids (N,), corners (N, 2) px, markers found).

        Tries, in order until one finds about as many corners as the previous frame: the
        tracked region, the whole reduced image, the whole image at full resolution.
        """
        H, W = gray.shape
        scale = _quantize_scale(min(1.0, self.cfg.max_side / max(H, W)), up=False)
        if self._scale_hint is not None:
            scale = _quantize_scale(self._scale_hint, up=True)
        # The cheap guess first (tracked region, one threshold window), then OpenCV's defaults.
        attempts = ([(self._roi, scale, self._window)] if self.cfg.track and self._roi is not None else [])
        attempts += [(None, scale, None)] + ([(None, 1.0, None)] if scale < 1.0 else [])
        best, used_scale = (None, None, 0, None), 1.0
        for roi, s, win in attempts:
            got = self._detect_in(gray, roi, s, win)
            if got[0] is not None and (best[0] is None or len(got[0]) > len(best[0])):
                best, used_scale = got, s
            elif best[0] is None:
                best = (None, None, max(best[2], got[2]), None)
            if best[0] is not None and len(best[0]) >= 0.8 * self._last_n:
                break
        roi = self._roi if best[3] is None else _region(best[1], best[3], (W, H))
        small = roi is not None and self._small_markers(best[2], best[3])
        if small:
            for s in self.cfg.upsample:
                if (roi[2] - roi[0]) * (roi[3] - roi[1]) * s * s > max(H * W, 1280 * 960):
                    break   # a board this large is not imaged too small; bounds the cost
                got = self._detect_in(gray, roi, s)
                if got[0] is not None and (best[0] is None or len(got[0]) > len(best[0])):
                    best, used_scale = got, s
        ids, corners, n_markers, mcs = best
        if ids is None:
            self.reset()
            return np.zeros(0, np.int32), np.zeros((0, 2)), n_markers
        if self.cfg.refine and used_scale < 1.0:
            # detectBoard refined them in the reduced image; sharpen them at full resolution.
            corners = self._refine(gray, corners, mcs, used_scale)
        if self.cfg.saddle and len(ids) >= 4:
            margins = corner_margins_px(self.board, ids, corners)
            half = np.clip(np.floor(self.cfg.saddle_frac * margins), 2, self.cfg.saddle_max).astype(np.int64)
            corners, _ = refine_saddles(gray, corners, half, self.cfg.saddle_blur)
            if small or np.median(margins) < self.cfg.xjunction_below:
                # Narrow white margins (low resolution, far or grazing views) leave the saddle
                # window 2-4 px (corners 0.03 px off at 640x480, up to 1.8 px at grazing
                # views); the X-junction fit reads the squares' edges instead (0.015 px). In
                # the enlarged search's frames a corner it cannot fit is dropped, not guessed.
                fit, fitted = refine_xjunctions(gray, self.board, ids, corners)
                ids, corners = (ids[fitted], fit[fitted]) if small else (ids, fit)
                if not len(ids):
                    self.reset()
                    return np.zeros(0, np.int32), np.zeros((0, 2)), n_markers
        self._last_n = len(ids)
        # Next frame: the smallest scale that keeps ``px_per_bit`` on all but the smallest
        # quarter of the markers, and a threshold window of ~0.4 marker side at that scale.
        sides = [np.linalg.norm(np.diff(np.vstack([m, m[:1]]), axis=0), axis=1).min() for m in mcs]
        self._scale_hint = self._window = None
        if sides:
            bits = self._cv_board.getDictionary().markerSize + 2
            side = max(float(np.percentile(sides, 25)), 1.0)
            self._scale_hint = float(np.clip(self.cfg.px_per_bit * bits / side, 0.25, 1.0))
            s = _quantize_scale(self._scale_hint, up=True)
            self._window = int(np.clip(0.4 * np.median(sides) * s, 5, 23)) | 1
        self._roi = _region(corners, mcs, (W, H))
        return ids, corners, n_markers

    def _small_markers(self, n_markers: int, marker_corners) -> bool:
        """Were markers missed because they are imaged too small to read (far or grazing
        views: a few px per bit)? Then an enlarged image finds them (bilinear/bicubic
        interpolation lets the adaptive threshold and the bit sampling resolve them)."""
        if not self.cfg.upsample or n_markers >= len(self._cv_board.getIds()):
            return False
        if not marker_corners:
            return True    # none read at all, in the region where the board last was
        bits = self._cv_board.getDictionary().markerSize + 2
        sides = [np.linalg.norm(np.diff(np.vstack([m, m[:1]]), axis=0), axis=1).min() for m in marker_corners]
        return float(np.median(sides)) / bits < self.cfg.upsample_below

    def _refine(self, gray: np.ndarray, corners: np.ndarray, marker_corners, scale: float) -> np.ndarray:
        """cornerSubPix at full resolution, with a window that stays inside the white margin
        between the saddle point and the nearest marker edge."""
        side = np.median([np.linalg.norm(np.diff(np.vstack([m, m[:1]]), axis=0), axis=1).mean()
                          for m in marker_corners]) if marker_corners else 0.0
        margin_px = side * (self.board.square_length - self.board.marker_length) / (2 * self.board.marker_length)
        half = int(np.clip(math.floor(self.cfg.win_frac * margin_px), 2, self.cfg.win_max))
        pts = corners.astype(np.float32).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.005)
        refined = cv2.cornerSubPix(gray, pts.copy(), (half, half), (-1, -1), crit).reshape(-1, 2)
        # A corner that wanders farther than the reduced image's pixel was pulled off by clutter.
        moved = np.linalg.norm(refined - corners, axis=1)
        max_move = max(1.5, 1.0 / scale)
        return np.where((moved < max_move)[:, None], refined.astype(np.float64), corners)


def _region(corners: np.ndarray, marker_corners, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """The board's region (x0, y0, x1, y1) px around found corners (N, 2) and marker corners, padded."""
    pts = np.concatenate([corners.reshape(-1, 2)] + [np.reshape(m, (-1, 2)) for m in marker_corners or []])
    lo, hi = pts.min(0), pts.max(0)
    pad = 0.25 * (hi - lo) + 24
    return (int(max(0, lo[0] - pad[0])), int(max(0, lo[1] - pad[1])),
            int(min(size[0], hi[0] + pad[0] + 1)), int(min(size[1], hi[1] + pad[1] + 1)))


def corner_margins_px(board: BoardSpec, ids: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Per corner (N,): the imaged width (px) of the white margin between a ChArUco corner and
    the nearest marker edge, along the board's more foreshortened axis (board-to-image
    homography through ``corners`` (N, 2) px of ChArUco ``ids`` (N,), N >= 4)."""
    obj = board.chessboard_corners()[ids][:, :2]
    H, _ = cv2.findHomography(obj, corners)
    if H is None:
        return np.zeros(len(ids))
    X = np.hstack([obj, np.ones((len(obj), 1))]) @ H.T
    w = X[:, 2:3]
    # d(image)/d(board x), d(image)/d(board y) at each corner, px per metre.
    jx = (H[None, :2, 0] * w - X[:, :2] * H[2, 0]) / w ** 2
    jy = (H[None, :2, 1] * w - X[:, :2] * H[2, 1]) / w ** 2
    px_per_m = np.minimum(np.linalg.norm(jx, axis=1), np.linalg.norm(jy, axis=1))
    return px_per_m * (board.square_length - board.marker_length) / 2


@lru_cache(maxsize=64)
def _saddle_operator(half: int, blur: float) -> np.ndarray:
    """(6, M*M), M = 2*(half + r) + 1: takes a patch centred on the current estimate, blurs it
    (Gaussian ``blur`` px, radius r = ceil(2 blur), 'valid' part) and returns the coefficients of
    a x^2 + b xy + c y^2 + d x + e y + f fitted by Gaussian-weighted least squares."""
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
    x, y = xx.ravel(), yy.ravel()
    A = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], 1)
    w = np.exp(-(x * x + y * y) / (2 * (0.6 * half + 0.5) ** 2))
    fit = np.linalg.pinv(A * w[:, None]) * w[None, :]           # (6, S*S)
    r = int(math.ceil(2 * blur)) if blur > 0 else 0
    S = 2 * half + 1
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / max(blur, 1e-6)) ** 2)
    K1 = np.zeros((S, S + 2 * r))
    for i in range(S):
        K1[i, i:i + 2 * r + 1] = k / k.sum()
    return fit @ np.kron(K1, K1)


def refine_saddles(gray: np.ndarray, corners: np.ndarray, half: np.ndarray, blur: float = 1.0,
                   iters: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Chessboard corners as saddle points of the image: a quadratic surface is fitted to the
    (Gaussian-blurred) grey levels around each corner and the estimate moved to its saddle,
    repeated until it stops moving. An X-junction is point-symmetric about its centre, so on a
    window centred there the fit's linear terms vanish: no bias from blur, perspective or the
    window size, unlike ``cornerSubPix`` on low-resolution corners.

    ``gray`` (H, W) uint8, ``corners`` (N, 2) px, ``half`` (N,) int window half-sizes (keep the
    window inside the white margin around the corner, see :func:`corner_margins_px`).
    Returns (corners (N, 2), refined (N,) bool); a corner whose fit is not a saddle, which
    would move more than half its window, or whose window the image border cuts keeps its
    input position.
    """
    corners = np.asarray(corners, np.float64).reshape(-1, 2)
    half = np.broadcast_to(np.asarray(half, np.int64), (len(corners),))
    out, ok = corners.copy(), np.zeros(len(corners), bool)
    H, W = gray.shape[:2]
    for i, ((x0, y0), h) in enumerate(zip(corners.tolist(), half.tolist())):
        P = _saddle_operator(h, float(blur))
        M = math.isqrt(P.shape[1])
        m = M // 2 + 1   # a window cut by the image border would not be symmetric
        if not (m <= x0 <= W - 1 - m and m <= y0 <= H - 1 - m):
            continue
        x, y, fitted = x0, y0, True
        for _ in range(iters):
            # getRectSubPix interpolates with float weights (remap rounds to 1/32 px).
            patch = cv2.getRectSubPix(gray, (M, M), (x, y), patchType=cv2.CV_32F)
            a, b, c, d, e, _ = (P @ patch.ravel()).tolist()
            det = 4 * a * c - b * b
            dx, dy = ((b * e - 2 * c * d) / det, (b * d - 2 * a * e) / det) if det < 0 else (h, h)
            if max(abs(dx), abs(dy)) >= h:   # not a saddle, or one outside the window
                fitted = False
                break
            x, y = x + dx, y + dy
            if max(abs(dx), abs(dy)) < 0.003:
                break
        if fitted and math.hypot(x - x0, y - y0) <= 0.5 * h:
            out[i], ok[i] = (x, y), True
    return out, ok


def _xjunction(p: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Blurred X-junction a + b W at offsets (dx, dy) (M,) px from the estimate, and its
    Jacobian (M, 7) in p = (cx, cy, theta1, theta2, a, b, s): two straight edges through (cx, cy)
    at angles theta1, theta2, Gaussian blur s px, W = 1 where the two sides differ."""
    cx, cy, t1, t2, a, b, s = p
    ex, ey = dx - cx, dy - cy
    s1, c1, s2, c2 = math.sin(t1), math.cos(t1), math.sin(t2), math.cos(t2)
    u1, u2 = (c1 * ey - s1 * ex) / s, (c2 * ey - s2 * ex) / s
    F1, F2 = 0.5 * (1 + erf(u1 / math.sqrt(2))), 0.5 * (1 + erf(u2 / math.sqrt(2)))
    g1 = np.exp(-0.5 * u1 * u1) / math.sqrt(2 * math.pi) * (1 - 2 * F2) * b
    g2 = np.exp(-0.5 * u2 * u2) / math.sqrt(2 * math.pi) * (1 - 2 * F1) * b
    W = F1 + F2 - 2 * F1 * F2
    J = np.stack([(g1 * s1 + g2 * s2) / s, -(g1 * c1 + g2 * c2) / s,
                  -g1 * (c1 * ex + s1 * ey) / s, -g2 * (c2 * ex + s2 * ey) / s,
                  np.ones_like(W), W, -(g1 * u1 + g2 * u2) / s], axis=1)
    return a + b * W, J


def refine_xjunctions(gray: np.ndarray, board: BoardSpec, ids: np.ndarray, corners: np.ndarray,
                      radius_max: float = 12.0, radius_frac: float = 0.45, marker_pad_px: float = 1.5,
                      iters: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """ChArUco corners by fitting a blurred X-junction model (:func:`_xjunction`: two edge
    lines, dark and light levels, blur) to every pixel within ``radius_frac`` of a square
    (at most ``radius_max`` px) around each corner, except the markers (dilated by
    ``marker_pad_px``), with Huber weights (parts hidden by the object or clutter).

    The saddle fit (:func:`refine_saddles`) must keep its window inside the white margin
    between corner and marker (2-4 px at 640x480); masking the markers instead lets the fit
    use the black squares' edges several times farther out: on synthetic footage the
    corner error halves (median 0.032 -> 0.015 px at 640x480) and the tail to 0.3-0.8 px
    goes. ~1 ms per corner, so it refines the views calibration uses, not every frame.

    ``gray`` (H, W) uint8; ``ids`` (N,), ``corners`` (N, 2) px (N >= 4, e.g. saddle points).
    Returns (corners (N, 2), refined (N,) bool); a corner whose fit fails, would move more
    than 1 px, or whose window leaves the image keeps its input position.
    """
    corners = np.asarray(corners, np.float64).reshape(-1, 2)
    out, ok = corners.copy(), np.zeros(len(corners), bool)
    obj = board.chessboard_corners()[ids][:, :2]
    H, _ = cv2.findHomography(obj, corners)
    if H is None or abs(np.linalg.det(H)) < 1e-12:
        return out, ok
    H_inv = np.linalg.inv(H)
    sq = board.square_length
    mg = (sq - board.marker_length) / 2
    img_h, img_w = gray.shape[:2]
    for i, ((X0, Y0), c) in enumerate(zip(obj, corners)):
        ends = cv2.perspectiveTransform(np.array([[[X0, Y0]], [[X0 + sq, Y0]], [[X0, Y0 + sq]]]), H).reshape(3, 2)
        vx, vy = ends[1] - ends[0], ends[2] - ends[0]
        sq_px = min(np.linalg.norm(vx), np.linalg.norm(vy))
        R = min(radius_max, radius_frac * sq_px)
        x0, x1 = math.floor(c[0] - R), math.ceil(c[0] + R)
        y0, y1 = math.floor(c[1] - R), math.ceil(c[1] + R)
        if R < 3 or x0 < 0 or y0 < 0 or x1 >= img_w or y1 >= img_h:
            continue
        yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
        v = gray[yy, xx].astype(np.float64).ravel()
        dx, dy = (xx - c[0]).ravel(), (yy - c[1]).ravel()
        keep = dx * dx + dy * dy <= R * R
        # Board position of each pixel relative to the corner: which square, and inside a marker?
        q = cv2.perspectiveTransform(np.stack([xx.ravel(), yy.ravel()], 1)[None].astype(np.float64), H_inv)[0]
        lx, ly = q[:, 0] - X0, q[:, 1] - Y0
        pad = marker_pad_px * sq / sq_px
        ax, ay = np.abs(lx), np.abs(ly)
        in_marker = (ax > mg - pad) & (ax < sq - mg + pad) & (ay > mg - pad) & (ay < sq - mg + pad)
        quad = (lx > 0).astype(int) * 2 + (ly > 0).astype(int)
        means = np.array([v[keep & (quad == k)].mean() if (keep & (quad == k)).any() else np.nan for k in range(4)])
        if not np.isfinite(means).all():
            continue
        white = means > np.median(means)          # the two squares that carry markers
        keep &= ~(in_marker & white[quad])
        if keep.sum() < 30:
            continue
        dx, dy, v = dx[keep], dy[keep], v[keep]
        dark, light = float(means[~white].mean()), float(means[white].mean())
        # Start from whichever assignment of the levels fits (W = 1 in the quadrants where
        # the two edge sides differ, which ones depends on how the board is imaged).
        p = np.array([0.0, 0.0, math.atan2(vx[1], vx[0]), math.atan2(vy[1], vy[0]), dark, light - dark, 0.8])
        alt = p.copy()
        alt[4], alt[5] = light, dark - light
        if np.sum((_xjunction(alt, dx, dy)[0] - v) ** 2) < np.sum((_xjunction(p, dx, dy)[0] - v) ** 2):
            p = alt
        fitted = False
        for _ in range(iters):
            f, J = _xjunction(p, dx, dy)
            r = v - f
            sigma = 1.4826 * float(np.median(np.abs(r))) + 1e-6
            w = np.minimum(1.0, 3 * sigma / (np.abs(r) + 1e-12))   # Huber
            A = J.T @ (J * w[:, None])
            try:
                step = np.linalg.solve(A + 1e-9 * np.trace(A) * np.eye(7), J.T @ (w * r))
            except np.linalg.LinAlgError:
                break
            p = p + step
            p[6] = min(max(p[6], 0.3), 3.0)   # Gauss-Newton overshoots the blur from a poor start
            if abs(p[0]) + abs(p[1]) > 2:
                break
            fitted = abs(step[0]) + abs(step[1]) < 1e-2   # the reweighting dithers below this
            if abs(step[0]) + abs(step[1]) < 1e-4:
                break
        if fitted and math.hypot(p[0], p[1]) <= 1.0:
            out[i], ok[i] = c + p[:2], True
    return out, ok


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


def detect_frames(frames, board: BoardSpec, cfg: DetectorConfig = DetectorConfig(),
                  tick: Callable[[], None] | None = None) -> list[Detection]:
    """Detect the board in an iterable of :class:`Frame` (grey or RGB), in order (tracking)."""
    det = BoardDetector(board, cfg)
    out = []
    for f in frames:
        gray = to_gray8(f.image)
        ids, corners, n_markers = det.detect(gray)
        out.append(Detection(f.index, f.time, f.name, ids, corners, n_markers, sharpness(gray)))
        if tick is not None:
            tick()
    return out


@dataclass(frozen=True)
class _Segment:
    source: FootageSource
    indices: tuple[int, ...]
    board: BoardSpec
    cfg: DetectorConfig


def _detect_segment(seg: _Segment) -> list[Detection]:
    """Worker: decode and detect one contiguous segment (runs in a spawned process)."""
    seg.source.single_thread = True
    return detect_frames(prefetched(seg.source.read(seg.indices, gray=True)), seg.board, seg.cfg, report)


def detect_footage(source: FootageSource, indices: Sequence[int], board: BoardSpec,
                   cfg: DetectorConfig = DetectorConfig(), workers: int = 1,
                   tick: Callable[[int], None] | None = None) -> list[Detection]:
    """Detect the board in frames ``indices`` of ``source``; ``workers`` > 1 splits the footage
    into that many contiguous segments, each decoded and detected in its own spawned process
    (one decoding thread each). In one process, PyAV's decoding threads run ahead of detection."""
    indices = list(indices)
    # A spawned worker costs about a second to start: only worth it on longer footage.
    workers = max(1, min(workers, len(indices) // 60 or 1))
    if workers == 1:
        return detect_frames(prefetched(source.read(indices, gray=True)), board, cfg,
                             (lambda: tick(1)) if tick else None)
    segments = [_Segment(source, c, board, cfg) for c in split(indices, workers)]
    results = map_spawned(_detect_segment, segments, workers, tick)
    return [d for r in results for d in r]


# --------------------------------------------------------------------------- diagnosis
# The smallest dictionary of each family: larger ones of a family begin with the same markers,
# and boards number their markers from 0, so these name the family quickly.
# (APRILTAG_36h10, slow to decode and rarely printed, is not probed.)
_PROBE_DICTIONARIES = ("DICT_4X4_50", "DICT_5X5_50", "DICT_6X6_50", "DICT_7X7_50",
                       "DICT_ARUCO_ORIGINAL", "DICT_ARUCO_MIP_36h12", "DICT_APRILTAG_16h5",
                       "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h11")


def _family(name: str) -> str:
    parts = name.split("_")
    return "_".join(parts[:2]) if parts[2:] and parts[-1].isdigit() else name


def diagnose_no_board(frames: Sequence[np.ndarray], board: BoardSpec) -> str:
    """Why no board was found in grey ``frames``: which dictionary's markers they show instead."""
    params = cv2.aruco.DetectorParameters()
    small = [g if max(g.shape) <= 960 else cv2.resize(g, None, fx=960 / max(g.shape), fy=960 / max(g.shape),
                                                      interpolation=cv2.INTER_AREA) for g in frames]
    own = board.dictionary
    names = [own] + [n for n in _PROBE_DICTIONARIES if _family(n) != _family(own)]
    counts: dict[str, int] = {}
    for name in names:
        det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)), params)
        counts[name] = sum(len(ids) for ids in (det.detectMarkers(g)[1] for g in small) if ids is not None)
    best = max(names[1:], key=lambda n: counts[n], default=own)
    if counts[own] > 0 and counts[best] <= counts[own]:
        return (f"{own} markers were found but no corners of a {board.squares_x}x"
                f"{board.squares_y} board: check squares_x, squares_y and legacy_pattern in board.json")
    if counts.get(best, 0) > 0:
        sized = f"{_family(best)}_* (e.g. {best})" if _family(best) != best else best
        return (f"the board's dictionary does not match: board.json says {own} but the frames "
                f"show {sized} markers ({counts[best]} found)")
    return "no ArUco markers of any dictionary were found (is the board in view and in focus?)"


# --------------------------------------------------------------------------- calibration
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


def _intrinsics(width: int, height: int, K: np.ndarray, dist: np.ndarray) -> Intrinsics:
    d = np.ravel(dist)
    return Intrinsics(width, height, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                      tuple(float(v) for v in d[:5]))


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
        return Calibration(_intrinsics(width, height, K, dist), float(rms), tuple(d.name for d in views),
                           tuple(rejected), float(std[0]), float(std[1]))
    intr = _intrinsics(width, height, K, dist)
    # Partly hidden corners pull the focal length and principal point as they pull poses.
    # A corner is off beyond 4 x the capture's typical residual (not a fixed 0.25 px: the
    # re-fitted corners are good to ~0.02 px, so 0.1-0.25 px is already far off).
    res = [np.linalg.norm(cv2.projectPoints(o, r, t, K, dist)[0].reshape(-1, 2) - i, axis=1)
           for o, i, r, t in zip(objs, imgs, rvecs, tvecs)]
    cfg = PoseConfig(corner_floor_px=4 * float(np.median(np.concatenate(res))) / 1.1774)
    keep = [_corner_inliers(o.astype(np.float64), i.astype(np.float64), _c2w(r, t), intr, cfg)
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
    return Calibration(_intrinsics(width, height, K, dist), float(rms), tuple(d.name for d in views),
                       tuple(rejected), fx_std, fy_std, bool(square), terms)


# --------------------------------------------------------------------------- poses
@dataclass(frozen=True)
class PoseConfig:
    """Gates. ``max_reproj_px``: per-frame RMS limit; ``ambiguity``: IPPE error ratio above
    which the two planar solutions are treated as a possible flip."""

    min_corners: int = 6
    max_reproj_px: float = 1.5
    ambiguity: float = 0.6
    outlier_window: int = 3
    outlier_deg: float = 3.0
    outlier_rel: float = 0.05     # position jump, as a fraction of the camera-board distance
    corner_k: float = 3.5         # a corner is dropped beyond k x the frame's typical residual ...
    corner_floor_px: float = 0.25  # ... and beyond this many px
    corner_drop: float = 0.3      # at most this fraction of a frame's corners is dropped
    path_window: int = 3          # fusion with the camera path: posed neighbours each side (0: off)


@dataclass(frozen=True)
class FramePose:
    """A frame's camera: ``c2w`` (4, 4) OpenCV board-from-camera (metres), or None with ``status``.

    ``status``: "posed", "arkit" (board hidden: the device's own pose, aligned to the board),
    or why there is none ("no board", "too few corners", "collinear corners", "reprojection",
    "outlier", "blurry").
    """

    index: int
    time: float
    name: str
    status: str
    c2w: np.ndarray | None = None
    n_corners: int = 0
    reproj_px: float = float("nan")
    ambiguity: float = float("nan")
    alt_c2w: np.ndarray | None = field(default=None, repr=False)  # the other planar solution
    inliers: np.ndarray | None = field(default=None, repr=False)  # (n_corners,) bool; None: all
    path_shift_mm: float = 0.0     # how far fusion with the camera path moved the camera (mm)

    @property
    def posed(self) -> bool:
        """Has a pose to use: from the board, or ("arkit") from the device's tracking."""
        return self.status in ("posed", "arkit")


def _rms(obj: np.ndarray, img: np.ndarray, rvec, tvec, K, dist) -> float:
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))


def _c2w(rvec, tvec) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
    return invert_rigid(rigid(R, np.ravel(tvec)))


def solve_pose(obj: np.ndarray, img: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, float, float, np.ndarray]:
    """Planar PnP for board points ``obj`` (N, 3) seen at ``img`` (N, 2) px.

    IPPE gives both planar solutions; each is LM-refined. Returns (c2w (4, 4), RMS px,
    ambiguity = RMS_best / RMS_other in (0, 1], c2w of the other solution).
    """
    K, dist = intr.K, intr.dist_array
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    sols = []
    for r, t in zip(rvecs[:n], tvecs[:n]):
        r, t = cv2.solvePnPRefineLM(obj, img, K, dist, r.copy(), t.copy())
        sols.append((_rms(obj, img, r, t, K, dist), r, t))
    sols.sort(key=lambda s: s[0])
    best = sols[0]
    other = sols[1] if len(sols) > 1 else sols[0]
    ratio = best[0] / other[0] if other[0] > 0 else 1.0
    return _c2w(best[1], best[2]), best[0], float(ratio), _c2w(other[1], other[2])


def _project(obj: np.ndarray, c2w: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Board points ``obj`` (N, 3) seen by camera ``c2w`` -> (N, 2) px (distorted)."""
    w2c = invert_rigid(c2w)
    proj, _ = cv2.projectPoints(obj, cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3], intr.K, intr.dist_array)
    return proj.reshape(-1, 2)


def _corner_inliers(obj: np.ndarray, img: np.ndarray, c2w: np.ndarray, intr: Intrinsics,
                    cfg: PoseConfig) -> np.ndarray | None:
    """Corners (N,) bool that fit pose ``c2w``, or None when all do (or too few would remain).

    A corner partly hidden (by the object, a finger, the frame edge) or caught on clutter sits
    pixels off while the rest agree to a few hundredths: one such corner tilts the whole pose.
    """
    res = np.linalg.norm(_project(obj, c2w, intr) - img, axis=1)
    sigma = float(np.median(res)) / 1.1774  # median of a 2D Gaussian's radius is 1.1774 sigma
    keep = res <= max(cfg.corner_k * sigma, cfg.corner_floor_px)
    if keep.all() or keep.sum() < max(cfg.min_corners, 4, math.ceil((1 - cfg.corner_drop) * len(res))):
        return None
    return keep


def pose_frames(dets: Sequence[Detection], board: BoardSpec, intr: Intrinsics,
                cfg: PoseConfig = PoseConfig()) -> list[FramePose]:
    """Pose every detection (independently; see :func:`reject_outliers` for the video pass)."""
    cv_board = board.cv_board()
    obj_all = board.chessboard_corners()
    out = []
    for d in dets:
        base = dict(index=d.index, time=d.time, name=d.name, n_corners=d.n_corners)
        if d.n_corners == 0:
            out.append(FramePose(status="no board", **base))
        elif d.n_corners < max(cfg.min_corners, 4):
            out.append(FramePose(status="too few corners", **base))
        elif cv_board.checkCharucoCornersCollinear(d.ids):
            out.append(FramePose(status="collinear corners", **base))
        else:
            obj, keep = obj_all[d.ids], None
            c2w, err, ratio, alt = solve_pose(obj, d.corners, intr)
            keep = _corner_inliers(obj, d.corners, c2w, intr, cfg)
            if keep is not None:
                c2w, err, ratio, alt = solve_pose(obj[keep], d.corners[keep], intr)
            status = "posed" if err <= cfg.max_reproj_px else "reprojection"
            out.append(FramePose(status=status, c2w=c2w, reproj_px=err, ambiguity=ratio,
                                 alt_c2w=alt, inliers=keep, **base))
    return out


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return math.degrees(math.acos(float(np.clip(c, -1, 1))))


def _local_fit(t: np.ndarray, y: np.ndarray, t0: float) -> np.ndarray:
    """Least-squares line through ``y`` (K, D) over times ``t`` (K,), evaluated at ``t0`` (D,)."""
    tc = t - t0
    V = np.stack([tc, np.ones_like(tc)], axis=1)
    coef, *_ = np.linalg.lstsq(V, y, rcond=None)
    return coef[-1]


def reject_outliers(poses: Sequence[FramePose], cfg: PoseConfig = PoseConfig()) -> list[FramePose]:
    """The video pass: resolve flipped planar solutions and reject poses that jump.

    Poses move smoothly, so each posed frame is compared with a polynomial fitted through
    its posed neighbours (``outlier_window`` each side, itself left out). Worst first, one at
    a time (so a bad frame cannot spoil its neighbours' verdicts): an ambiguous frame whose
    other IPPE solution fits the prediction takes it; otherwise a frame farther than
    ``outlier_deg`` or ``outlier_rel`` x distance, plus twice the neighbours' typical step
    per frame, is marked "outlier".
    """
    out = list(poses)
    active = [i for i, p in enumerate(out) if p.posed]
    w = cfg.outlier_window

    def excess(i: int, c2w: np.ndarray, j: int, C: np.ndarray, T: np.ndarray) -> float:
        """How far ``c2w`` (frame at position j of the active list) is beyond its threshold (>1: out)."""
        nb = [k for k in range(max(0, j - w), min(len(T), j + w + 1)) if k != j]
        y = np.concatenate([C[nb, :3, 3], C[nb, :3, 2]], axis=1)  # position, viewing direction
        pred = _local_fit(T[nb], y, T[j])
        dir_ref = pred[3:] / (np.linalg.norm(pred[3:]) + 1e-12)
        # How far the camera moves per frame here sets the scale of a normal deviation.
        steps = np.linalg.norm(np.diff(y[:, :3], axis=0), axis=1)
        turns = np.degrees(np.arccos(np.clip(np.sum(y[1:, 3:] * y[:-1, 3:], axis=1), -1, 1)))
        ang = math.degrees(math.acos(float(np.clip(c2w[:3, 2] @ dir_ref, -1, 1))))
        jump = float(np.linalg.norm(c2w[:3, 3] - pred[:3]))
        limit = cfg.outlier_rel * float(np.linalg.norm(c2w[:3, 3])) + 2 * float(np.median(steps))
        return max(ang / (cfg.outlier_deg + 2 * float(np.median(turns))), jump / limit)

    for _ in range(len(active)):
        if len(active) < 4:
            break
        C = np.stack([out[i].c2w for i in active])
        T = np.array([out[i].time for i in active])
        scores = [excess(i, C[j], j, C, T) for j, i in enumerate(active)]
        j = int(np.argmax(scores))
        if scores[j] <= 1.0:
            break
        i = active[j]
        p = out[i]
        if p.ambiguity > cfg.ambiguity and p.alt_c2w is not None and excess(i, p.alt_c2w, j, C, T) <= 1.0:
            out[i] = replace(p, c2w=p.alt_c2w, alt_c2w=p.c2w)
        else:
            out[i] = replace(p, status="outlier")
            active.pop(j)
    return out


def _moved(c2w: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``c2w`` turned by the world-frame rotation vector ``x[:3]`` (rad) and moved by ``x[3:]`` (m)."""
    return rigid(cv2.Rodrigues(np.asarray(x[:3], np.float64))[0] @ c2w[:3, :3], c2w[:3, 3] + x[3:6])


def _path_offsets(c2ws: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Poses (K, 4, 4) as 6-vectors relative to ``ref``: world-frame rotation vector (rad) taking
    ``ref``'s rotation to theirs, and camera-centre offset (m); the inverse of :func:`_moved`."""
    rot = [cv2.Rodrigues(C[:3, :3] @ ref[:3, :3].T)[0].ravel() for C in c2ws]
    return np.concatenate([np.array(rot).reshape(-1, 3), c2ws[:, :3, 3] - ref[:3, 3]], axis=1)


def _path_prediction(t: np.ndarray, y: np.ndarray, var: np.ndarray, t0: float) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares polynomial (degree 2, or 1 with fewer than 5 points) through
    ``y`` (K, D) with variances ``var`` (K, D) over times ``t`` (K,), per component, evaluated
    at ``t0``: (prediction (D,), its variance (D,))."""
    tc = t - t0
    V = np.stack([tc ** k for k in range(2 if len(t) >= 5 else 1, -1, -1)], axis=1)
    pred, pvar = np.empty(y.shape[1]), np.empty(y.shape[1])
    for c in range(y.shape[1]):
        A = np.linalg.pinv(V.T @ (V / var[:, c:c + 1]))
        pred[c] = (A @ (V.T @ (y[:, c] / var[:, c])))[-1]
        pvar[c] = A[-1, -1]
    return pred, pvar


def _jacobian(f: Callable[[np.ndarray], np.ndarray], x: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """Forward-difference Jacobian of ``f`` at ``x`` (the residuals here are smooth in radians
    and metres at this step)."""
    f0 = f(x)
    return np.stack([(f(x + e) - f0) / eps for e in np.eye(len(x)) * eps], axis=1)


# chi-square with 6 degrees of freedom, 99.9 %: a frame further than this from its path, in
# its own and the path's uncertainty, moved with the camera (a real jerk), not by error.
_CHI2_6_999 = 22.46


def fuse_with_path(dets: Sequence[Detection], poses: Sequence[FramePose], board: BoardSpec,
                   intr: Intrinsics, cfg: PoseConfig = PoseConfig()) -> list[FramePose]:
    """Board poses fused with the camera's path (a fixed-lag smoother for video).

    A frame that sees a handful of corners in one corner of the board pins the camera down
    poorly along some directions (16 mm off at 0.7 m from 6 corners), and the crop centre moves
    with it; its neighbours, seeing the board well, say where the camera was. Each posed
    frame's pose is re-solved from its corners together with what its ``path_window`` posed
    neighbours each side predict (a polynomial in time, itself left out), each weighed by its
    uncertainty, in 6 components (world-frame rotation vector, camera centre):

    - a frame's own uncertainty: its corners' Jacobian, with the capture's typical per-frame
      RMS as the corners' noise (or the frame's own, where larger); the neighbours' fit is
      weighted by theirs, so a weak neighbour hardly moves the prediction;
    - the path's: the prediction's variance plus how unevenly the camera moves (per component,
      the median excess of prediction-minus-measurement over what both uncertainties explain);
    - a frame further from its path than both explain (chi-square, 99.9 %) keeps its pose: the
      camera really moved so.

    A frame whose corners pin its pose down keeps it; a weak one moves along its weak
    directions. Neighbours enter as measured, not as fused. ``path_shift_mm`` records each move.
    """
    w = cfg.path_window
    active = [i for i, p in enumerate(poses) if p.status == "posed"]
    if w <= 0 or len(active) < 4:
        return list(poses)
    by_index = {d.index: d for d in dets}
    if any(poses[i].index not in by_index for i in active):
        return list(poses)
    obj_all = board.chessboard_corners().astype(np.float64)
    typical_px = max(float(np.median([poses[i].reproj_px for i in active])) / math.sqrt(2.0), 0.02)

    def reprojection(i: int) -> tuple[Callable[[np.ndarray], np.ndarray], float]:
        """The frame's corner residuals in units of their noise, and that noise (px): the
        capture's typical, or the frame's own where larger (its residual sum over the 2N - 6
        degrees of freedom the pose leaves: with few corners the pose hides half of the error)."""
        p, d = poses[i], by_index[poses[i].index]
        keep = slice(None) if p.inliers is None else p.inliers
        obj, img = obj_all[d.ids][keep], d.corners[keep].astype(np.float64)
        own = math.sqrt(len(obj) * p.reproj_px ** 2 / max(2 * len(obj) - 6, 1))
        sigma = max(typical_px, own)
        return (lambda x: ((_project(obj, _moved(p.c2w, x), intr) - img) / sigma).ravel()), sigma

    funcs, sigmas = zip(*[reprojection(i) for i in active])
    zero = np.zeros(6)
    J0 = [_jacobian(f, zero) for f in funcs]
    var_meas = np.array([np.diag(np.linalg.pinv(J.T @ J)) for J in J0])          # (A, 6)
    C = np.stack([poses[i].c2w for i in active])
    T = np.array([poses[i].time for i in active])
    nbs = [[k for k in range(max(0, j - w), min(len(active), j + w + 1)) if k != j] for j in range(len(active))]
    offsets = [_path_offsets(C[nb], C[j]) for j, nb in enumerate(nbs)]
    q = np.zeros(6)
    for _ in range(2):  # the path's unevenness from the first pass's predictions, then again
        fits = [_path_prediction(T[nb], y, var_meas[nb] + q, T[j]) for j, (nb, y) in enumerate(zip(nbs, offsets))]
        pred = np.array([f[0] for f in fits])
        var_pred = np.array([f[1] for f in fits])
        excess = pred ** 2 - var_meas - var_pred
        q = np.maximum(np.median(excess, axis=0) / 0.455, 1e-12)
    var_prior = var_pred + q
    out = list(poses)
    for j, i in enumerate(active):
        if float(np.sum(pred[j] ** 2 / (var_meas[j] + var_prior[j]))) > _CHI2_6_999:
            continue
        f, wprior = funcs[j], 1.0 / np.sqrt(var_prior[j])

        def residuals(x: np.ndarray) -> np.ndarray:
            return np.concatenate([f(x), (x - pred[j]) * wprior])

        x = np.zeros(6)
        for _ in range(5):  # Gauss-Newton; nearly linear this close to the measured pose
            dx = np.linalg.lstsq(_jacobian(residuals, x), -residuals(x), rcond=None)[0]
            x = x + dx
            if np.abs(dx).max() < 1e-9:
                break
        p = poses[i]
        c2w = _moved(p.c2w, x)
        err = float(np.sqrt(np.mean(np.sum(f(x).reshape(-1, 2) ** 2, axis=1)))) * sigmas[j]
        out[i] = replace(p, c2w=c2w, reproj_px=err, path_shift_mm=float(np.linalg.norm(x[3:]) * 1000))
    return out


def fill_from_device(poses: Sequence[FramePose], device_c2w: np.ndarray, min_aligned: int = 3) -> list[FramePose]:
    """Frames without a board pose take the device's own pose (Record3D's ARKit track,
    OpenCV camera axes, (N, 4, 4) indexed by frame), mapped into the board frame by the rigid
    transform that best aligns the device track with the board poses of the posed frames."""
    board_posed = [p for p in poses if p.status == "posed" and p.index < len(device_c2w)]
    if len(board_posed) < min_aligned:
        return list(poses)
    # board_from_device = c2w_board @ inv(c2w_device), averaged: rotation by SVD, translation by median.
    Ts = np.stack([p.c2w @ invert_rigid(device_c2w[p.index]) for p in board_posed])
    U, _, Vt = np.linalg.svd(Ts[:, :3, :3].sum(0))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    board_from_device = rigid(R, np.median(Ts[:, :3, 3], axis=0))
    out = []
    for p in poses:
        if p.status in ("no board", "too few corners", "collinear corners") and p.index < len(device_c2w):
            p = FramePose(p.index, p.time, p.name, "arkit", board_from_device @ device_c2w[p.index],
                          p.n_corners)
        out.append(p)
    return out


def refine_jointly(dets: Sequence[Detection], poses: Sequence[FramePose], board: BoardSpec,
                   intr: Intrinsics, square_pixels: bool = False,
                   dist_terms: str = ALL_DIST_TERMS) -> tuple[Intrinsics, list[FramePose], float]:
    """Bundle adjustment with the board corners as known 3D points: intrinsics and every posed
    frame's pose refined together (OpenCV's LM in ``calibrateCamera``, started from the current
    intrinsics and poses; ``square_pixels`` keeps fx/fy as it is). Distortion terms missing from
    ``dist_terms`` stay 0: the calibration's test found no support for them, and freeing them
    here lets the principal point drift. Returns (intrinsics, poses, RMS px)."""
    by_index = {d.index: d for d in dets}
    posed = [p for p in poses if p.posed]
    if len(posed) < 3:
        return intr, list(poses), float("nan")
    obj_all = board.chessboard_corners().astype(np.float32)
    # Each frame's corners that its own pose fit (see _corner_inliers).
    sel = [slice(None) if p.inliers is None else p.inliers for p in posed]
    objs = [obj_all[by_index[p.index].ids][s] for p, s in zip(posed, sel)]
    imgs = [by_index[p.index].corners[s].astype(np.float32) for p, s in zip(posed, sel)]
    rvecs, tvecs = [], []
    for p in posed:
        w2c = invert_rigid(p.c2w)
        rvecs.append(cv2.Rodrigues(w2c[:3, :3])[0])
        tvecs.append(w2c[:3, 3].reshape(3, 1).copy())
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_USE_EXTRINSIC_GUESS
    flags |= cv2.CALIB_FIX_ASPECT_RATIO if square_pixels else 0
    terms = set(dist_terms.split())
    flags |= 0 if "k3" in terms else cv2.CALIB_FIX_K3
    flags |= 0 if {"p1", "p2"} <= terms else cv2.CALIB_ZERO_TANGENT_DIST
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        objs, imgs, (intr.width, intr.height), intr.K.copy(), intr.dist_array.copy(),
        rvecs, tvecs, flags=flags)
    new = _intrinsics(intr.width, intr.height, K, dist)
    refined = {p.index: (_c2w(r, t), o, i) for p, r, t, o, i in zip(posed, rvecs, tvecs, objs, imgs)}
    out = []
    for p in poses:
        if p.index in refined:
            c2w, o, i = refined[p.index]
            w2c = invert_rigid(c2w)
            err = _rms(o.astype(np.float64), i.astype(np.float64), cv2.Rodrigues(w2c[:3, :3])[0],
                       w2c[:3, 3], new.K, new.dist_array)
            p = replace(p, c2w=c2w, reproj_px=err)
        out.append(p)
    return new, out, float(rms)


# --------------------------------------------------------------------------- whole footage
def detect_sampled(source: FootageSource, board: BoardSpec, fps: float | None = None,
                   det_cfg: DetectorConfig = DetectorConfig(), workers: int = 1,
                   tick: Callable[[int], None] | None = None,
                   total: Callable[[int], None] | None = None) -> list[Detection]:
    """Detections in the frames of ``source`` resampled to ``fps``.

    Raises :class:`DbbError` when no frame shows the board, naming the dictionary seen instead.
    """
    from ..capture.footage import sample_indices

    idx = sample_indices(source.info.times, fps)
    if total:
        total(len(idx))
    dets = detect_footage(source, idx, board, det_cfg, workers, tick)
    if not any(d.n_corners for d in dets):
        probe = [f.image for f in source.read(idx[np.linspace(0, len(idx) - 1, min(3, len(idx))).astype(int)],
                                              gray=True)]
        raise DbbError(f"no ChArUco board found in any of {len(dets)} frames of {source.info.path}: "
                       + diagnose_no_board(probe, board))
    return dets


def calibrate_footage(source: FootageSource, board: BoardSpec, fps: float | None = None,
                      max_views: int = 40, blur_ratio: float = 0.4, workers: int = 1,
                      tick: Callable[[int], None] | None = None,
                      total: Callable[[int], None] | None = None,
                      precise: bool = False) -> Calibration:
    """Intrinsics of the camera that filmed ``source`` (sharp frames only).

    By default OpenCV's calibration (``cornerSubPix`` corners, see :func:`calibrate`), so the
    result agrees with OpenCV's tools; ``precise``: saddle-point corners, off-pose corners
    dropped, square pixels, the chosen views' corners re-fitted by :func:`refine_xjunctions`
    and distortion terms the corners do not call for left out (see docs/benchmarks.md).
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

@dataclass(frozen=True)
class PoseRun:
    """Everything the pose stage found: intrinsics (and where they came from), every sampled
    frame's pose or the reason it has none, and the blurred frames that were dropped."""

    intrinsics: Intrinsics
    intrinsics_source: str         # "camera.json", "calibrated (RMS 0.21 px)", "record3d"
    frames: tuple[FramePose, ...]
    detections: tuple[Detection, ...]
    calibration: Calibration | None = None
    refined_rms: float | None = None
    frames_in_footage: int = 0     # before sampling to --fps

    @property
    def posed(self) -> list[FramePose]:
        return [p for p in self.frames if p.posed]


def estimate_poses(source: FootageSource, board: BoardSpec, intr: Intrinsics | None = None,
                   fps: float | None = None, blur_ratio: float = 0.4, refine: bool = False,
                   workers: int = 1, det_cfg: DetectorConfig = DetectorConfig(),
                   pose_cfg: PoseConfig = PoseConfig(), min_posed: int = 3,
                   tick: Callable[[int], None] | None = None, total: Callable[[int], None] | None = None,
                   intr_source: str = "camera.json", device_c2w: np.ndarray | None = None,
                   calib_views: int = 100) -> PoseRun:
    """Frames of ``source`` -> metric camera poses in the board frame (see module doc).

    ``device_c2w`` (N, 4, 4): the device's own poses (Record3D), used where the board is hidden.
    Without ``intr``, the intrinsics are calibrated from at most ``calib_views`` diverse frames.
    Raises :class:`DbbError` when no frame shows the board (naming the dictionary seen
    instead) or fewer than ``min_posed`` frames can be posed.
    """
    info = source.info
    dets = detect_sampled(source, board, fps, det_cfg, workers, tick, total)
    blurry = blurry_mask(np.array([d.sharpness for d in dets]), blur_ratio)
    calib = None
    if intr is None:
        # Calibrating from the capture itself: every diverse view tightens the focal length.
        calib = calibrate_precise(source, [d for d, b in zip(dets, blurry) if not b], board, calib_views)
        intr, intr_source = calib.intrinsics, f"calibrated from the footage (RMS {calib.rms:.3f} px)"
    elif (intr.width, intr.height) != (info.width, info.height):
        raise DbbError(f"camera.json is for {intr.width}x{intr.height} but the footage is "
                       f"{info.width}x{info.height}")
    sharp = [d for d, b in zip(dets, blurry) if not b]
    poses = reject_outliers(pose_frames(sharp, board, intr, pose_cfg), pose_cfg)
    refined_rms = None
    if refine:
        intr, poses, refined_rms = refine_jointly(
            sharp, poses, board, intr, calib is not None and calib.square_pixels,
            calib.dist_terms if calib is not None else ALL_DIST_TERMS)
        poses = reject_outliers(poses, pose_cfg)
    poses = fuse_with_path(sharp, poses, board, intr, pose_cfg)
    if device_c2w is not None:
        poses = fill_from_device(poses, device_c2w)
    by_index = {p.index: p for p in poses}
    frames = tuple(by_index.get(d.index) or FramePose(d.index, d.time, d.name, "blurry",
                                                      n_corners=d.n_corners) for d in dets)
    n_posed = sum(p.status == "posed" for p in frames)
    if n_posed < min_posed:
        why = {}
        for p in frames:
            why[p.status] = why.get(p.status, 0) + 1
        raise DbbError(f"only {n_posed} of {len(frames)} frames could be posed (need {min_posed}): "
                       + ", ".join(f"{k}: {v}" for k, v in sorted(why.items())))
    return PoseRun(intr, intr_source, frames, tuple(dets), calib, refined_rms, info.n_frames)
