"""Sub-pixel corners: saddle points and X-junction fits."""

from __future__ import annotations

import cv2
import numpy as np

from dbb_capture.geometry.cameras import project_points
from dbb_capture.poses.corners import refine_saddles, refine_xjunctions
from dbb_capture.poses.detect import BoardDetector, DetectorConfig

from .conftest import BOARD, x_junction


def test_saddle_refinement_finds_skewed_blurred_corners():
    """Saddle points land on the true corner to ~0.02 px from 0.8 px away, however the edges
    are skewed; a patch without a saddle (a straight edge) leaves its corner where it was."""
    for k, (centre, angles) in enumerate([((20.3, 19.8), (0, 90)), ((20.71, 20.45), (20, 75)),
                                          ((19.6, 20.2), (-35, 40)), ((20.0, 20.5), (10, 150))]):
        img = x_junction(centre, angles, seed=k)
        start = np.array([[centre[0] + 0.6, centre[1] - 0.5]])
        got, ok = refine_saddles(img, start, np.array([5]))
        assert ok[0] and np.linalg.norm(got[0] - centre) < 0.03, (angles, got[0])
    yy, xx = np.mgrid[0:41, 0:41]
    edge = np.where(xx > 20.3, 200, 30).astype(np.uint8)
    got, ok = refine_saddles(cv2.GaussianBlur(edge, (0, 0), 1.2), np.array([[20.0, 20.0]]), np.array([5]))
    assert not ok[0] and np.allclose(got, [[20.0, 20.0]])
    # A window the image border would cut is not fitted (it would not be symmetric).
    img = x_junction((4.3, 20.0), (0, 90))
    got, ok = refine_saddles(img, np.array([[4.0, 20.0]]), np.array([5]))
    assert not ok[0] and np.allclose(got, [[4.0, 20.0]])


def test_saddle_corners_beat_opencv_corners(rendered):
    """On rendered views the saddle refinement halves OpenCV's corner error."""
    intr, views = rendered
    err = {True: [], False: []}
    for saddle in (True, False):
        for c2w, gray in views:
            ids, corners, _ = BoardDetector(BOARD, DetectorConfig(saddle=saddle)).detect(gray)
            truth = project_points(BOARD.chessboard_corners()[ids], c2w, intr)
            err[saddle].append(np.linalg.norm(corners - truth, axis=1))
    new, old = np.median(np.concatenate(err[True])), np.median(np.concatenate(err[False]))
    assert new < 0.7 * old and new < 0.06, (new, old)


def test_xjunction_fit_beats_saddle_corners(rendered):
    """Fitting the X-junction over the black squares' edges (markers masked) halves the
    saddle points' corner error on rendered views; a corner too near the image border keeps
    its position. At these white margins (under 6 px) the detector itself re-fits them."""
    intr, views = rendered
    err = {"saddle": [], "xj": [], "detector": []}
    for c2w, gray in views:
        ids, corners, _ = BoardDetector(BOARD, DetectorConfig(xjunction_below=0.0)).detect(gray)
        truth = project_points(BOARD.chessboard_corners()[ids], c2w, intr)
        refined, ok = refine_xjunctions(gray, BOARD, ids, corners)
        assert ok.mean() > 0.9
        err["saddle"].append(np.linalg.norm(corners - truth, axis=1))
        err["xj"].append(np.linalg.norm(refined - truth, axis=1))
        ids, corners, _ = BoardDetector(BOARD).detect(gray)
        err["detector"].append(np.linalg.norm(corners - project_points(BOARD.chessboard_corners()[ids], c2w, intr), axis=1))
    new, old = np.median(np.concatenate(err["xj"])), np.median(np.concatenate(err["saddle"]))
    assert new < 0.7 * old and new < 0.03, (new, old)
    assert np.median(np.concatenate(err["detector"])) < 0.7 * old
    c2w, gray = views[0]
    ids, corners, _ = BoardDetector(BOARD).detect(gray)
    shifted = corners - corners[:1] + [3.0, 3.0]    # the first corner 3 px from the image corner
    got, ok = refine_xjunctions(gray, BOARD, ids, shifted)
    assert not ok[0] and np.allclose(got[0], shifted[0])
