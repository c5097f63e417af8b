"""A fixed camera without a board: the temporal median room, one window."""

from __future__ import annotations

import json

import cv2
import numpy as np
from click.testing import CliRunner
from dbb_capture.cli.capture import main

from dbb_capture.datasets.transforms import load_dataset
from dbb_capture.geometry.cameras import project_points


def test_fixed_camera_mode_mattes_a_moving_ball(tmp_path):
    """No board, a camera that never moves: the temporal median is the room, the window is cut as is."""
    cap = tmp_path / "fixed"
    (cap / "frames").mkdir(parents=True)
    rng = np.random.default_rng(0)
    room = cv2.GaussianBlur(rng.integers(60, 200, (120, 160, 3), dtype=np.uint8), (0, 0), 3)
    truth = []
    for i in range(30):
        img = room.copy()
        cx, cy = 80 + int(30 * np.sin(i / 3)), 70
        cv2.circle(img, (cx, cy), 9, (220, 40, 40), -1)
        m = np.zeros((120, 160), np.uint8)
        cv2.circle(m, (cx, cy), 9, 255, -1)
        truth.append(m[30:110, 40:120])
        cv2.imwrite(str(cap / "frames" / f"{i:04d}.png"), img[..., ::-1])
    ds = tmp_path / "ds"
    res = CliRunner().invoke(main, ["preprocess", str(cap), "-o", str(ds), "--crop-window", "40,30,80",
                                    "--crop-size", "80", "--sequence-length", "5"])
    assert res.exit_code == 0, res.output
    crops = json.loads((ds / "crops.json").read_text())
    assert len(crops["frames"]) == 30 and crops["fixed_camera"]["window"] == [40, 30, 80]
    assert len({json.dumps(f["viewpoint"]) for f in crops["frames"]}) == 1   # one constant viewpoint
    # The recorded crop camera is the one the window's pixels came from: the object centre (on the
    # window's centre ray, below the frame's) projects to the crop's centre, the ball to its place.
    f0 = load_dataset(ds).frames[0]
    assert np.allclose(project_points(np.array([crops["object"]["center"]]), f0.c2w, f0.intr), 39.5, atol=1e-6)
    ious = []
    for f, t in zip(crops["frames"], truth):
        a = cv2.imread(str(ds / f["file_path"]), cv2.IMREAD_UNCHANGED)[..., 3] > 127
        ious.append((a & (t > 127)).sum() / (a | (t > 127)).sum())
    assert np.median(ious) > 0.9, ious
    bad = CliRunner().invoke(main, ["preprocess", str(cap), "-o", str(tmp_path / "x"), "--crop-window", "500,0,50"])
    assert bad.exit_code == 2 and "outside" in bad.output


def test_fixed_camera_mode_on_real_pendulum_footage(tmp_path):
    from conftest import shared_data

    video = shared_data("pendulum", "ball.mp4")
    ds = tmp_path / "ds"
    res = CliRunner().invoke(main, ["preprocess", str(video.parent), "-o", str(ds), "--crop-window", "0,270,360",
                                    "--no-matte", "--fps", "10"])
    assert res.exit_code == 0, res.output
    stats = json.loads((ds / "dataset.json").read_text())
    assert stats["crops"] > 100 and stats["sequences"]["train"] > 50 and stats["touching_border"] == 0
