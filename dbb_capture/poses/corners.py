"""Sub-pixel ChArUco corners: saddle points of the image and straight-edge X-junction fits."""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np
from scipy.special import erf

from ..capture.board import BoardSpec


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
