"""Poses fused with the camera path (a smooth path's prediction against each frame's corners),
the device's own poses where the board is hidden, and joint refinement of intrinsics and poses."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Callable, Sequence

import cv2
import numpy as np

from ..capture.board import BoardSpec
from ..geometry.cameras import Intrinsics, project_points
from ..geometry.transforms import c2w_from_rvec_tvec, invert_rigid, rigid
from .calibrate import ALL_DIST_TERMS
from .detect import Detection
from .solve import FramePose, PoseConfig, reprojection_rms


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
        return (lambda x: ((project_points(obj, _moved(p.c2w, x), intr) - img) / sigma).ravel()), sigma

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
        if p.status in ("no board", "too few corners", "collinear corners", "no pose solution") and p.index < len(device_c2w):
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
    new = Intrinsics.from_matrix(intr.width, intr.height, K, dist)
    refined = {p.index: (c2w_from_rvec_tvec(r, t), o, i) for p, r, t, o, i in zip(posed, rvecs, tvecs, objs, imgs)}
    out = []
    for p in poses:
        if p.index in refined:
            c2w, o, i = refined[p.index]
            w2c = invert_rigid(c2w)
            err = reprojection_rms(o.astype(np.float64), i.astype(np.float64), cv2.Rodrigues(w2c[:3, :3])[0],
                       w2c[:3, 3], new.K, new.dist_array)
            p = replace(p, c2w=c2w, reproj_px=err)
        out.append(p)
    return new, out, float(rms)
