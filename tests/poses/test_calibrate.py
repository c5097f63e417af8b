"""Calibration: OpenCV's real photos, synthetic views, square pixels, bad input."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import shared_data
from dbb_capture.cli.capture import main

from dbb_capture.capture.board import BoardSpec
from dbb_capture.capture.footage import FootageFrame
from dbb_capture.geometry.cameras import Intrinsics, project_points
from dbb_capture.geometry.transforms import look_at
from dbb_capture.poses.calibrate import calibrate, intrinsics_fit
from dbb_capture.poses.detect import Detection, detect_frames
from dbb_capture.poses.solve import pose_frames

REAL_BOARD = {"squares_x": 5, "squares_y": 7, "square_length": 0.04, "marker_length": 0.02,
              "dictionary": "DICT_6X6_250"}


@pytest.fixture()
def real_photos(tmp_path) -> Path:
    """img_00..03.jpg linked into a folder of their own, beside a board.json."""
    src = shared_data("charuco_opencv")
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(4):
        (photos / f"img_0{i}.jpg").symlink_to((src / f"img_0{i}.jpg").resolve())
    (tmp_path / "board.json").write_text(json.dumps(REAL_BOARD))
    return photos


def _reference() -> tuple[np.ndarray, np.ndarray]:
    fs = cv2.FileStorage(str(shared_data("charuco_opencv", "tutorial_camera_charuco.yml")),
                         cv2.FILE_STORAGE_READ)
    return fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat().ravel()


def test_real_photos_match_opencv_calibration(real_photos, tmp_path):
    out = tmp_path / "camera.json"
    res = CliRunner().invoke(main, ["calibrate", str(real_photos), "--board",
                                    str(tmp_path / "board.json"), "-o", str(out)])
    assert res.exit_code == 0, res.output
    cam = json.loads(out.read_text())
    K_ref, _ = _reference()
    # The bar: OpenCV's calibration of the same four photos, fx and fy within 1.5%.
    assert abs(cam["fx"] / K_ref[0, 0] - 1) < 0.015
    assert abs(cam["fy"] / K_ref[1, 1] - 1) < 0.015
    assert cam["rms"] <= 0.3 and (cam["width"], cam["height"]) == (640, 480)
    assert cam["fx_std"] < 0.05 * cam["fx"] and cam["fy_std"] < 0.05 * cam["fy"]
    # --precise (saddle corners, off-pose corners dropped, square pixels) fits the corners more
    # closely; four photos fix the focal length only to ~3%, so it lands within 3 of OpenCV's
    # own standard deviations of the reference, not within 1.5%.
    precise = tmp_path / "precise.json"
    res = CliRunner().invoke(main, ["calibrate", str(real_photos), "--board", str(tmp_path / "board.json"),
                                    "-o", str(precise), "--precise"])
    assert res.exit_code == 0, res.output
    pre = json.loads(precise.read_text())
    assert pre["rms"] < cam["rms"]
    assert abs(pre["fx"] - K_ref[0, 0]) < 3 * cam["fx_std"] and abs(pre["fy"] - K_ref[1, 1]) < 3 * cam["fy_std"]
    # The occluded photo (a hand over the board) is still posed with these intrinsics.
    board = BoardSpec.from_json(REAL_BOARD)
    img = cv2.imread(str(shared_data("charuco_opencv", "chocclusion_original.jpg")), cv2.IMREAD_GRAYSCALE)
    dets = detect_frames([FootageFrame(0, 0.0, img, "occluded")], board)
    pose = pose_frames(dets, board, Intrinsics.from_json(cam))[0]
    assert pose.posed and pose.n_corners >= 10 and pose.reproj_px < 1.0
    assert pose.n_corners < len(board.chessboard_corners())   # part of the board really is hidden


def _synthetic_detections(intr: Intrinsics, board: BoardSpec, n: int = 10, noise_px: float = 0.1):
    """Board corners projected from ``n`` known poses (exact projection plus pixel noise)."""
    rng = np.random.default_rng(7)
    obj = board.chessboard_corners()
    dets = []
    for i in range(n):
        a, e = math.radians(-60 + 120 * i / (n - 1)), math.radians(35 + 35 * (i % 3) / 2)
        d = 0.45 + 0.1 * (i % 2)
        eye = board.center + d * np.array([math.sin(a) * math.cos(e), -math.cos(a) * math.cos(e), -math.sin(e)])
        target = board.center + rng.normal(0, 0.05, 3) * [1, 1, 0]
        c2w = look_at(eye, target, np.array([0.0, 0.0, -1.0]))
        uv = project_points(obj, c2w, intr) + rng.normal(0, noise_px, (len(obj), 2))
        inside = (uv[:, 0] > 0) & (uv[:, 0] < intr.width - 1) & (uv[:, 1] > 0) & (uv[:, 1] < intr.height - 1)
        ids = np.flatnonzero(inside).astype(np.int32)
        dets.append(Detection(i, i / 10, f"{i:05d}", ids, uv[ids], 17, 100.0))
    return dets


def test_synthetic_calibration_recovers_camera_and_rejects_bad_view():
    board = BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100")
    truth = Intrinsics(1280, 960, 1100.0, 1100.0, 641.3, 478.2, (-0.15, 0.08, 0.001, -0.0005, 0.0))
    dets = _synthetic_detections(truth, board)
    d = dets[4]
    # A view whose corners are mislabelled by one id: a plausible detection gone wrong.
    dets[4] = Detection(d.index, d.time, d.name, d.ids, np.roll(d.corners, 1, axis=0), 17, 100.0)
    cal = calibrate(dets, board, truth.width, truth.height)
    assert cal.rejected == ("00004",)
    i = cal.intrinsics
    assert abs(i.fx / truth.fx - 1) < 0.005 and abs(i.fy / truth.fy - 1) < 0.005
    assert abs(i.cx - truth.cx) < 3 and abs(i.cy - truth.cy) < 3
    assert abs(i.dist[0] - truth.dist[0]) < 0.02
    assert "p1 p2" in cal.dist_terms   # this lens is decentred: the test keeps p1, p2
    assert 0.05 < cal.rms < 0.2   # the injected pixel noise, not more
    # Fewer diverse views when asked: the selection spreads over the sweep.
    few = calibrate(dets[:4] + dets[5:], board, truth.width, truth.height, max_views=5)
    assert len(few.used) == 5 and abs(few.intrinsics.fx / truth.fx - 1) < 0.02


def test_square_pixels_unless_the_corners_say_otherwise():
    """fx = fy is imposed when the corners allow it (tighter principal point), never when the
    camera's pixels are not square; corners pulled off by a hidden edge are dropped."""
    board = BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100")
    square = Intrinsics(1280, 960, 1100.0, 1100.0, 641.3, 478.2, (-0.15, 0.08, 0.0, 0.0, 0.0))
    dets = _synthetic_detections(square, board, n=16, noise_px=0.05)
    d = dets[3]
    off = d.corners.copy()
    off[5] += [1.2, 0.9]                      # one corner partly hidden
    dets[3] = Detection(d.index, d.time, d.name, d.ids, off, 17, 100.0)
    cal = calibrate(dets, board, square.width, square.height)
    assert cal.square_pixels and cal.intrinsics.fx == cal.intrinsics.fy
    # No decentring and no k3 in this lens: the corners do not call for them, so they stay 0.
    assert cal.dist_terms == "k1 k2" and cal.intrinsics.dist[2:] == (0.0, 0.0, 0.0)
    assert abs(cal.intrinsics.fx / square.fx - 1) < 3 * cal.fx_std / square.fx + 1e-4
    assert abs(cal.intrinsics.cx - square.cx) < 1.0 and abs(cal.intrinsics.cy - square.cy) < 1.0
    assert cal.rms < 0.1   # the hidden corner does not count
    wide = Intrinsics(1280, 960, 1133.0, 1100.0, 641.3, 478.2, (-0.15, 0.08, 0.0, 0.0, 0.0))
    cal = calibrate(_synthetic_detections(wide, board, n=16, noise_px=0.05), board, wide.width, wide.height)
    assert not cal.square_pixels
    assert abs(cal.intrinsics.fx / cal.intrinsics.fy - 1.03) < 0.002


def test_given_intrinsics_misfit_only_when_far_off(real_photos):
    """Given intrinsics against a quick calibration of the same views: the true camera and
    OpenCV's own calibration of its photos fit (within 1.1 x), a focal length 1.5 x off does not."""
    board = BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100")
    truth = Intrinsics(640, 480, 530.0, 530.0, 319.7, 240.2, (-0.15, 0.08, 0.0, 0.0, 0.0))
    dets = _synthetic_detections(truth, board, n=12, noise_px=0.05)
    fit = intrinsics_fit(dets, board, truth)
    assert not fit.misfit and fit.views == 12 and fit.given_rms < 1.1 * fit.calibrated_rms
    off = intrinsics_fit(dets, board, replace(truth, fx=1.5 * truth.fx, fy=1.5 * truth.fy))
    assert off.misfit and off.given_rms > 0.5 and off.calibrated_rms == fit.calibrated_rms
    assert intrinsics_fit(dets[:3], board, truth) is None            # too few views to judge
    real = BoardSpec.from_json(REAL_BOARD)
    frames = [FootageFrame(i, float(i), cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), p.stem)
              for i, p in enumerate(sorted(real_photos.iterdir()))]
    K, dist = _reference()
    fit = intrinsics_fit(detect_frames(frames, real), real, Intrinsics.from_matrix(640, 480, K, dist))
    assert not fit.misfit and fit.views == 4 and fit.given_rms < 1.1 * fit.calibrated_rms


@pytest.mark.parametrize("case", ["no_board_flag", "wrong_dictionary", "bad_board_json"])
def test_calibrate_bad_input_exits_2(real_photos, tmp_path, case):
    args = ["calibrate", str(real_photos), "-o", str(tmp_path / "cam.json")]
    expect = {"no_board_flag": "--board", "wrong_dictionary": "DICT_6X6_",
              "bad_board_json": "squares_y is missing"}[case]
    if case == "wrong_dictionary":
        (tmp_path / "b4.json").write_text(json.dumps({**REAL_BOARD, "dictionary": "DICT_4X4_50"}))
        args += ["--board", str(tmp_path / "b4.json")]
    elif case == "bad_board_json":
        (tmp_path / "bad.json").write_text(json.dumps({"squares_x": 5}))
        args += ["--board", str(tmp_path / "bad.json")]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and expect in lines[0], res.output


def test_precise_corners_make_a_partly_hidden_view_drop_out():
    """With corners good to 0.02 px, a view whose every other corner is 0.2 px off (half the
    board behind the object) is left out: more than may be dropped corner by corner, and far
    under the 1-px floor that guards OpenCV's own fit."""
    board = BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100")
    cam = Intrinsics(1280, 960, 1100.0, 1100.0, 641.3, 478.2, (-0.15, 0.08, 0.0, 0.0, 0.0))
    dets = _synthetic_detections(cam, board, n=16, noise_px=0.02)
    d = dets[6]
    off = d.corners.copy()
    ang = np.random.default_rng(3).uniform(0, 2 * math.pi, len(off[::2]))
    off[::2] += 0.2 * np.stack([np.cos(ang), np.sin(ang)], 1)
    dets[6] = Detection(d.index, d.time, d.name, d.ids, off, 17, 100.0)
    cal = calibrate(dets, board, cam.width, cam.height)
    assert "00006" in cal.rejected and "00006" not in cal.used
    assert cal.rms < 0.03
