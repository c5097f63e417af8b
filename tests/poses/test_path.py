"""The camera path: device poses, fusion with the path, joint refinement."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dbb_capture.capture.footage import FootageFrame
from dbb_capture.geometry.cameras import project_points
from dbb_capture.poses.detect import Detection, detect_frames
from dbb_capture.poses.path import fuse_with_path, refine_jointly
from dbb_capture.poses.solve import FramePose, PoseConfig, pose_frames
from dbb_capture.synth.scene import SynthConfig

from .conftest import BOARD, smooth_path, view_c2w


def test_device_poses_fill_frames_without_board():
    """Record3D: where the board is hidden, the ARKit pose mapped into the board frame is used."""
    from dbb_capture.geometry.transforms import invert_rigid, rigid
    from dbb_capture.poses.path import fill_from_device

    poses = smooth_path(8)
    board_from_device = rigid(cv2.Rodrigues(np.array([0.3, -1.2, 0.5]))[0], [1.0, -2.0, 0.5])
    device = np.stack([invert_rigid(board_from_device) @ p.c2w for p in poses])
    hidden = poses[6]
    poses[6] = FramePose(hidden.index, hidden.time, hidden.name, "no board")
    out = fill_from_device(poses, device)
    assert out[6].status == "arkit" and out[6].posed
    np.testing.assert_allclose(out[6].c2w, hidden.c2w, atol=1e-9)
    assert [p.status for p in out].count("posed") == 7


def test_weak_pose_is_fused_with_the_path_and_a_real_jerk_stays():
    """A frame that sees 6 corners in one corner of the board (one of them 0.6 px off) is pulled
    onto its neighbours' path; a frame where the camera really leaves the smooth path (seen
    whole) keeps its step; the rest, smoothed, are no worse on average."""
    intr = SynthConfig(width=480, height=360, board=BOARD, dist=(-0.12, 0.05, 0.001, -0.001, 0.0)).intrinsics()
    rng = np.random.default_rng(4)
    obj = BOARD.chessboard_corners()
    truth, dets, weak, jerk = [], [], 7, 3
    for i in range(15):
        c2w = view_c2w(-40 + 5 * i, 50, 0.6, BOARD.center)
        if i == jerk:
            c2w[:3, 3] += [0.004, -0.003, 0.0]                 # a real 5 mm step off the path
        ids = np.array([0, 1, 2, 6, 7, 8]) if i == weak else np.arange(len(obj))
        corners = project_points(obj[ids], c2w, intr) + rng.normal(0, 0.1, (len(ids), 2))
        if i == weak:
            corners[5] += [0.6, 0.0]
        truth.append(c2w)
        dets.append(Detection(i, i / 10, f"{i:05d}", ids, corners, 17, 1.0))
    measured = pose_frames(dets, BOARD, intr)
    fused = fuse_with_path(dets, measured, BOARD, intr)
    err = lambda ps, i: float(np.linalg.norm(ps[i].c2w[:3, 3] - truth[i][:3, 3]) * 1000)  # mm
    assert all(p.posed for p in fused)
    assert err(measured, weak) > 3.0                            # the weak frame is really off
    assert err(fused, weak) < 0.2 * err(measured, weak)
    assert fused[weak].path_shift_mm > 3.0
    assert err(fused, jerk) < 1.0                               # 5 mm off the path, and kept
    strong = [i for i in range(15) if i != weak]
    assert np.mean([err(fused, i) for i in strong]) <= np.mean([err(measured, i) for i in strong])
    off = fuse_with_path(dets, measured, BOARD, intr, PoseConfig(path_window=0))
    assert all(np.array_equal(a.c2w, b.c2w) for a, b in zip(off, measured))


def test_joint_refinement_keeps_the_calibrations_distortion_terms(rendered):
    """Terms the calibration left out (k3, p1, p2) stay 0 in the bundle adjustment; all five move
    when all five were fitted."""
    intr, views = rendered
    dets = detect_frames([FootageFrame(k, k / 10, g, f"{k:05d}") for k, (_, g) in enumerate(views)], BOARD)
    poses = pose_frames(dets, BOARD, intr)
    assert sum(p.posed for p in poses) == len(views)
    kept, _, rms = refine_jointly(dets, poses, BOARD, intr, True, "k1 k2")
    assert rms < 0.3 and kept.dist[2:] == (0.0, 0.0, 0.0) and kept.fx == pytest.approx(kept.fy)
    free, _, _ = refine_jointly(dets, poses, BOARD, intr)
    assert all(v != 0.0 for v in free.dist)
