"""Per-frame camera poses in the board frame: planar PnP (IPPE, then LM), flip check, corner and
reprojection gates, and outlier rejection along the video."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import cv2
import numpy as np

from ..capture.board import BoardSpec
from ..geometry.cameras import Intrinsics, project_points
from ..geometry.transforms import c2w_from_rvec_tvec
from .detect import Detection


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
    or why there is none ("no board", "too few corners", "collinear corners", "no pose solution",
    "reprojection", "outlier", "blurry").
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


def reprojection_rms(obj: np.ndarray, img: np.ndarray, rvec, tvec, K, dist) -> float:
    """RMS (px) of board points ``obj`` (N, 3) projected with OpenCV's ``rvec``/``tvec`` against ``img`` (N, 2)."""
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))


def solve_pose(obj: np.ndarray, img: np.ndarray,
               intr: Intrinsics) -> tuple[np.ndarray, float, float, np.ndarray] | None:
    """Planar PnP for board points ``obj`` (N, 3) seen at ``img`` (N, 2) px.

    IPPE gives both planar solutions; each is LM-refined. Returns (c2w (4, 4), RMS px,
    ambiguity = RMS_best / RMS_other in (0, 1], c2w of the other solution), or None when IPPE
    finds no solution (e.g. all corners but one on a line: OpenCV's collinearity check passes,
    the homography is degenerate).
    """
    K, dist = intr.K, intr.dist_array
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not n:
        return None
    sols = []
    for r, t in zip(rvecs[:n], tvecs[:n]):
        r, t = cv2.solvePnPRefineLM(obj, img, K, dist, r.copy(), t.copy())
        sols.append((reprojection_rms(obj, img, r, t, K, dist), r, t))
    sols.sort(key=lambda s: s[0])
    best = sols[0]
    other = sols[1] if len(sols) > 1 else sols[0]
    ratio = best[0] / other[0] if other[0] > 0 else 1.0
    return c2w_from_rvec_tvec(best[1], best[2]), best[0], float(ratio), c2w_from_rvec_tvec(other[1], other[2])


def corner_inliers(obj: np.ndarray, img: np.ndarray, c2w: np.ndarray, intr: Intrinsics,
                    cfg: PoseConfig) -> np.ndarray | None:
    """Corners (N,) bool that fit pose ``c2w``, or None when all do (or too few would remain).

    A corner partly hidden (by the object, a finger, the frame edge) or caught on clutter sits
    pixels off while the rest agree to a few hundredths: one such corner tilts the whole pose.
    """
    res = np.linalg.norm(project_points(obj, c2w, intr) - img, axis=1)
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
            sol = solve_pose(obj, d.corners, intr)
            if sol is not None:
                keep = corner_inliers(obj, d.corners, sol[0], intr, cfg)
                if keep is not None:
                    sol = solve_pose(obj[keep], d.corners[keep], intr)
            if sol is None:
                out.append(FramePose(status="no pose solution", **base))
                continue
            c2w, err, ratio, alt = sol
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
