"""Per-frame poses: the flip check, the gates, corners off by pixels."""

from __future__ import annotations

import cv2
import numpy as np
from conftest import rotation_error_deg

from dbb_capture.capture.footage import FootageFrame
from dbb_capture.geometry.cameras import project_points
from dbb_capture.poses.detect import Detection, detect_frames
from dbb_capture.poses.solve import FramePose, PoseConfig, pose_frames, reject_outliers

from .conftest import BOARD, smooth_path


def test_flipped_solution_is_resolved_and_jumps_rejected():
    poses = smooth_path()
    true5 = poses[5].c2w
    flipped = true5.copy()
    # The planar ambiguity mirrors the view direction about the line of sight to the board.
    flipped[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.6, 0.0]))[0] @ true5[:3, :3]
    p = poses[5]
    poses[5] = FramePose(p.index, p.time, p.name, "posed", flipped, 20, 0.2, 0.9, true5)
    jump = poses[8].c2w.copy()
    jump[:3, 3] += [0.4, 0.0, 0.0]
    p = poses[8]
    poses[8] = FramePose(p.index, p.time, p.name, "posed", jump, 20, 0.2, 0.1, jump)
    out = reject_outliers(poses, PoseConfig())
    np.testing.assert_allclose(out[5].c2w, true5)
    assert out[5].posed
    assert out[8].status == "outlier"
    assert sum(p.posed for p in out) == len(poses) - 1


def test_gates(rendered):
    intr, views = rendered
    dets = detect_frames([FootageFrame(0, 0.0, views[1][1], "a")], BOARD)
    d = dets[0]
    few = type(d)(1, 0.1, "b", d.ids[:3], d.corners[:3], 2, 1.0)
    none = type(d)(2, 0.2, "c", d.ids[:0], d.corners[:0], 0, 1.0)
    bad = type(d)(3, 0.3, "d", d.ids, d.corners + np.random.default_rng(1).normal(0, 3, d.corners.shape), 9, 1.0)
    out = pose_frames([d, few, none, bad], BOARD, intr, PoseConfig())
    assert [p.status for p in out] == ["posed", "too few corners", "no board", "reprojection"]


def test_corner_off_by_pixels_is_dropped(rendered):
    """A corner pulled 2 px off (partly hidden) is dropped before the final solve."""
    intr, views = rendered
    c2w = views[1][0]
    ids = np.arange(len(BOARD.chessboard_corners()))
    corners = project_points(BOARD.chessboard_corners(), c2w, intr)
    corners = corners + np.random.default_rng(1).normal(0, 0.03, corners.shape)
    corners[7] += [1.5, -1.3]
    det = Detection(0, 0.0, "00000", ids, corners, 17, 1.0)
    pose = pose_frames([det], BOARD, intr)[0]
    assert pose.posed and pose.inliers is not None
    assert not pose.inliers[7] and pose.inliers.sum() == len(ids) - 1
    plain = pose_frames([det], BOARD, intr, PoseConfig(corner_floor_px=1e9))[0]
    assert plain.inliers is None
    assert rotation_error_deg(pose.c2w[:3, :3], c2w[:3, :3]) < 0.5 * rotation_error_deg(plain.c2w[:3, :3], c2w[:3, :3])


def test_corners_without_planar_solution_leave_the_frame_unposed():
    """Five corners of the first row and one of the second (a real synthetic frame): OpenCV's
    collinearity check passes but IPPE finds no solution; the frame is counted as not posed."""
    from dbb_capture.geometry.cameras import Intrinsics

    intr = Intrinsics(320, 240, 265.25, 265.25, 159.52, 119.12, (-0.0019, -0.0032, 0.0, 0.0, 0.0))
    ids = np.array([1, 2, 3, 4, 5, 9])
    corners = np.array([[268.399, 177.932], [241.007, 173.526], [214.820, 169.258], [189.786, 165.233],
                        [165.766, 161.362], [216.525, 157.341]])
    det = Detection(16, 2.0, "00016", ids, corners, 6, 1.0)
    assert [p.status for p in pose_frames([det], BOARD, intr)] == ["no pose solution"]
