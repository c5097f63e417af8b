"""Poses on a sphere, OpenCV's board pose and the true silhouette of the object."""

from __future__ import annotations

import cv2
import numpy as np

from dbb_capture.capture.board import BoardSpec
from dbb_capture.geometry.transforms import invert_rigid, look_at
from dbb_capture.synth.objects import UP


def pose_on_sphere(center, dist, az_deg, el_deg, roll_deg=0.0):
    az, el = np.radians(az_deg), np.radians(el_deg)
    fwd, side = np.array([0.0, -1, 0]), np.array([1.0, 0, 0])
    eye = center + dist * (np.cos(el) * (np.cos(az) * fwd + np.sin(az) * side) + np.sin(el) * UP)
    c2w = look_at(eye, center, UP)
    Rz, _ = cv2.Rodrigues(np.array([0, 0, np.radians(roll_deg)]))
    c2w[:3, :3] = c2w[:3, :3] @ Rz
    return c2w


def solve_board_pose(gray, board: BoardSpec, intr):
    det = cv2.aruco.CharucoDetector(board.cv_board())
    corners, ids, _, _ = det.detectBoard(gray)
    assert ids is not None and len(ids) >= 12, "board not detected"
    obj, img = board.cv_board().matchImagePoints(corners, ids)
    ok, rvec, tvec = cv2.solvePnP(obj, img, intr.K, intr.dist_array, flags=cv2.SOLVEPNP_IPPE)
    assert ok
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, intr.K, intr.dist_array, rvec, tvec)
    w2c = np.eye(4)
    w2c[:3, :3] = cv2.Rodrigues(rvec)[0]
    w2c[:3, 3] = tvec.ravel()
    return invert_rigid(w2c), len(ids)


def silhouette_mask(model, t, c2w, intr, n=720):
    """The object's silhouette drawn from projected contour points of every ellipsoid (H, W) bool.

    Independent of the renderer's ray casting: the contour of an ellipsoid seen from a point
    is the circle where the polar plane of the eye cuts it (in the ellipsoid's unit-sphere
    frame); its points are projected with cv2.projectPoints (distortion included) and filled.
    """
    from matplotlib.path import Path as PolyPath

    w2c = invert_rigid(c2w)
    rvec = cv2.Rodrigues(w2c[:3, :3])[0]
    mask = np.zeros((intr.height, intr.width), bool)
    for c, R, e in model.posed(t):
        r = np.asarray(e.radii)
        o = (R.T @ (c2w[:3, 3] - c)) / r
        o2 = o @ o
        center, rho = o / o2, np.sqrt(1 - 1 / o2)
        a = np.cross(o, [1.0, 0, 0] if abs(o[0]) < 0.9 * np.sqrt(o2) else [0, 1.0, 0])
        a /= np.linalg.norm(a)
        b = np.cross(o / np.sqrt(o2), a)
        th = np.linspace(0, 2 * np.pi, n, endpoint=False)
        q = center + rho * (np.cos(th)[:, None] * a + np.sin(th)[:, None] * b)
        pts = c + (q * r) @ R.T
        uv, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, w2c[:3, 3], intr.K, intr.dist_array)
        # A pixel is inside when its centre (integer coordinates, OpenCV) is inside the contour.
        uv = uv.reshape(-1, 2)
        x0, y0 = np.maximum(np.floor(uv.min(0)).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(uv.max(0)).astype(int) + 1, [intr.width, intr.height])
        if x1 <= x0 or y1 <= y0:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        inside = PolyPath(uv).contains_points(np.stack([xx.ravel(), yy.ravel()], 1).astype(float))
        mask[y0:y1, x0:x1] |= inside.reshape(yy.shape)
    return mask
