"""The poses stage through the command: its files, calibration, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import rotation_error_deg
from dbb_capture.cli.capture import main

from dbb_capture.capture.board import BoardSpec
from dbb_capture.geometry.conventions import opencv_from_opengl


def o3d_points(path: Path) -> np.ndarray:
    """The points (N, 3) of a PLY as open3d reads it (nerfstudio's splatfacto reads it so)."""
    import open3d as o3d

    pcd = o3d.io.read_point_cloud(str(path))
    assert pcd.has_colors()
    return np.asarray(pcd.points)


def test_preprocess_stop_after_poses(distorted_capture, tmp_path):
    ds = tmp_path / "ds"
    res = CliRunner().invoke(main, ["preprocess", str(distorted_capture), "-o", str(ds), "--stop-after", "poses",
                                    "--camera", str(distorted_capture / "ground_truth" / "camera.json")])
    assert res.exit_code == 0, res.output
    tf = json.loads((ds / "transforms.json").read_text())
    gt = json.loads((distorted_capture / "ground_truth" / "cameras.json").read_text())["video"]
    assert tf["camera_model"] == "OPENCV" and tf["k1"] == 0.0 and tf["up"] == [0.0, 0.0, -1.0]
    assert len(tf["frames"]) >= 7
    rot = []
    for fr in tf["frames"]:
        assert (ds / fr["file_path"]).is_file()
        i = int(Path(fr["file_path"]).stem)
        assert fr["time"] == pytest.approx(gt[i]["time"])
        est = opencv_from_opengl(np.array(fr["transform_matrix"]))
        true = opencv_from_opengl(np.array(gt[i]["transform_matrix"]))
        rot.append(rotation_error_deg(est[:3, :3], true[:3, :3]))
        # Plumbing check: 320x240 frames with 6-12 corners each (accuracy: the rendered sweep above).
        assert np.linalg.norm(est[:3, 3] - true[:3, 3]) < 0.03
    assert np.median(rot) < 0.4 and max(rot) < 1.5
    # Files use the corner origin (a centred camera has cx = w / 2), as COLMAP does: one principal point.
    import pycolmap

    rec = pycolmap.Reconstruction(str(ds / "colmap" / "sparse" / "0"))
    assert rec.num_images() == len(tf["frames"])
    cam = rec.cameras[1]
    cam_json = json.loads((ds / "camera.json").read_text())
    assert cam.params[2] == pytest.approx(tf["cx"]) and tf["cx"] == pytest.approx(cam_json["cx"] + 0.5)
    assert tf["applied_transform"] == np.eye(4)[:3].tolist()     # no axis swap for nerfstudio to insert
    im = next(iter(rec.images.values()))
    fr = next(f for f in tf["frames"] if f["file_path"] == "images/" + im.name)     # COLMAP's image path: images/
    w2c = np.linalg.inv(opencv_from_opengl(np.array(fr["transform_matrix"])))
    np.testing.assert_allclose(im.cam_from_world().matrix(), w2c[:3], atol=1e-6)
    # The board's corners: a point cloud (PLY, named in transforms.json) and COLMAP points whose
    # observations are where the poses project them (the detected, undistorted corners).
    pc = o3d_points(ds / tf["ply_file_path"])
    board = BoardSpec.load(distorted_capture / "board.json")
    assert 6 <= len(pc) <= len(board.chessboard_corners()) and np.abs(pc[:, 2]).max() < 1e-6
    assert rec.num_points3D() == len(pc)
    errs = []
    for pid, pt in rec.points3D.items():
        assert pt.track.length() >= 1
        for el in pt.track.elements:
            image = rec.images[el.image_id]
            uv = image.project_point(pt.xyz)                        # COLMAP's pixels (corner origin)
            errs.append(np.linalg.norm(uv - image.points2D[el.point2D_idx].xy))
    assert np.median(errs) < 0.5 and max(errs) < 3, (np.median(errs), max(errs))
    report = json.loads((ds / "poses" / "report.json").read_text())
    assert report["frames_posed"] == len(tf["frames"]) and report["frames_sampled"] == 10
    assert all("corners" in f and f["sharpness"] > 0 for f in report["frames"])
    assert report["frames_in_footage"] == 10
    assert (ds / "poses" / "camera_path.png").stat().st_size > 10_000
    plot = cv2.imread(str(ds / "poses" / "camera_path.png")).astype(int)      # BGR
    reddish = (plot[..., 2] > plot[..., 1] + 40) & (plot[..., 2] > plot[..., 0] + 40)
    assert reddish.sum() > 200                       # the object sphere (object.json), in both views
    assert "frames posed, the board's corners land " in res.output and "(under 1 px is good)" in res.output
    assert json.loads((ds / "preprocess.json").read_text())["stages_run"] == ["poses"]


def test_preprocess_calibrates_when_no_camera_json(distorted_capture, tmp_path):
    ds = tmp_path / "ds"
    res = CliRunner().invoke(main, ["preprocess", str(distorted_capture), "-o", str(ds), "--refine",
                                    "--stop-after", "poses"])
    assert res.exit_code == 0, res.output
    cam = json.loads((ds / "camera.json").read_text())
    true = json.loads((distorted_capture / "ground_truth" / "camera.json").read_text())
    # Seven small views calibrate loosely; calibration accuracy is tested in test_calibrate.py.
    assert abs(cam["fx"] / true["fx"] - 1) < 0.15 and cam["rms"] < 0.5
    assert "calibrated" in json.loads((ds / "poses" / "report.json").read_text())["intrinsics_source"]


def test_a_camera_json_that_does_not_fit_is_refused_before_the_poses(distorted_capture, tmp_path):
    """A focal length 1.5 x wrong: one line with both figures, from a handful of views, nothing written."""
    cam = json.loads((distorted_capture / "ground_truth" / "camera.json").read_text())
    (tmp_path / "camera.json").write_text(json.dumps(cam | {"fx": 1.5 * cam["fx"], "fy": 1.5 * cam["fy"]}))
    res = CliRunner().invoke(main, ["preprocess", str(distorted_capture), "-o", str(tmp_path / "ds"),
                                    "--camera", str(tmp_path / "camera.json")])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert "camera.json does not fit this footage: board reprojection " in lines[0]
    assert " px with its intrinsics, " in lines[0] and "recalibrate or omit camera.json" in lines[0]
    assert not (tmp_path / "ds").exists()


@pytest.mark.parametrize("case", ["bad_board", "wrong_dictionary", "unknown_stage", "exists"])
def test_preprocess_bad_input_exits_2(distorted_capture, tmp_path, case):
    args = ["preprocess", str(distorted_capture), "-o", str(tmp_path / "ds")]
    if case == "bad_board":
        (tmp_path / "board.json").write_text("{not json")
        args += ["--board", str(tmp_path / "board.json")]
    elif case == "wrong_dictionary":
        (tmp_path / "board.json").write_text(json.dumps(
            {"squares_x": 5, "squares_y": 4, "square_length": 0.07, "marker_length": 0.05,
             "dictionary": "DICT_6X6_250"}))
        args += ["--board", str(tmp_path / "board.json"), "--fps", "2"]
    elif case == "unknown_stage":
        args += ["--stop-after", "matting"]
    else:
        (tmp_path / "ds").mkdir()
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1, res.output
    expect = {"bad_board": "not valid JSON", "wrong_dictionary": "DICT_4X4_",
              "unknown_stage": "unknown stage", "exists": "already exists"}[case]
    assert expect in lines[0]
