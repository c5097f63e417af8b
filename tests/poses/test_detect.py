"""Board detection: the fast path, the dictionary named, workers, small grazing boards."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dbb_capture.capture.board import BoardSpec
from dbb_capture.capture.footage import FootageFrame
from dbb_capture.geometry.cameras import project_points
from dbb_capture.poses.detect import (
    BoardDetector,
    DetectorConfig,
    detect_frames,
    diagnose_no_board,
)
from dbb_capture.synth.render import Renderer, sensor
from dbb_capture.synth.scene import SynthConfig, make_scene

from .conftest import BOARD, view_c2w


def test_fast_path_agrees_with_plain_detection(rendered):
    """Reduced-image detection with full-resolution refinement and tracking finds the same corners."""
    intr, views = rendered
    plain = DetectorConfig(max_side=10_000, track=False, refine=False)
    fast = DetectorConfig(max_side=240, track=True, refine=True)
    frames = [FootageFrame(i, i / 10, g, f"{i:05d}") for i, (_, g) in enumerate(views)]
    frames = frames + frames[::-1]  # revisit views so the tracked region is used and must move
    a = detect_frames(frames, BOARD, plain)
    b = detect_frames(frames, BOARD, fast)
    for da, db, f in zip(a, b, frames):
        common, ia, ib = np.intersect1d(da.ids, db.ids, return_indices=True)
        assert len(common) >= 0.8 * len(da.ids)
        c2w = views[f.index][0]
        truth = project_points(BOARD.chessboard_corners()[common], c2w, intr)
        assert np.median(np.linalg.norm(db.corners[ib] - truth, axis=1)) < 0.2


def test_dictionary_mismatch_is_named(rendered):
    _, views = rendered
    wrong = BoardSpec(7, 5, 0.05, 0.0375, "DICT_6X6_250")
    grays = [views[1][1]]
    assert len(BoardDetector(wrong).detect(grays[0])[0]) == 0
    msg = diagnose_no_board(grays, wrong)
    assert "DICT_5X5_" in msg and "DICT_6X6_250" in msg
    wrong_size = BoardSpec(9, 8, 0.05, 0.0375, "DICT_5X5_100")
    assert "squares_x" in diagnose_no_board(grays, wrong_size) or len(BoardDetector(wrong_size).detect(grays[0])[0])


def test_worker_processes_return_every_frame_in_order(tmp_path, rendered):
    """Two spawned workers split the footage and return the same detections as one process."""
    from fractions import Fraction

    import av

    from dbb_capture.capture.footage import VideoSource
    from dbb_capture.poses.detect import detect_footage

    _, views = rendered
    path = tmp_path / "v.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=Fraction(30))
        s.width, s.height, s.pix_fmt = 480, 360, "yuv420p"
        s.options = {"crf": "12", "g": "30"}
        for i in range(120):
            g = views[(i // 30) % len(views)][1]
            for p in s.encode(av.VideoFrame.from_ndarray(np.stack([g] * 3, -1), format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    src = VideoSource(path)
    ticks = []
    two = detect_footage(src, range(120), BOARD, workers=2, tick=ticks.append)
    assert [d.index for d in two] == list(range(120)) and sum(ticks) == 120
    assert [d.time for d in two] == pytest.approx(np.arange(120) / 30)
    assert min(d.n_corners for d in two) >= 12


def test_small_grazing_board_is_read_enlarged():
    """A far, grazing view (markers ~1 px per bit across): OpenCV reads a few markers; the
    detector searches the board's region enlarged and re-fits the corners as X-junctions."""
    cfg = SynthConfig(width=480, height=360, board=BOARD, dist=(-0.12, 0.05, 0.0, 0.0, 0.0))
    rng = np.random.default_rng(3)
    intr = cfg.intrinsics()
    c2w = view_c2w(55, 25, 0.85, BOARD.center)
    img, _ = Renderer(intr, 2).render(make_scene(cfg, rng), c2w, 0.0)
    gray = cv2.cvtColor(sensor(img, 0.01, rng), cv2.COLOR_RGB2GRAY)
    plain = DetectorConfig(upsample=())
    n_plain = len(BoardDetector(BOARD, plain).detect(gray)[0])
    ids, corners, _ = BoardDetector(BOARD).detect(gray)
    assert len(ids) >= max(8, n_plain + 4)
    err = np.linalg.norm(corners - project_points(BOARD.chessboard_corners()[ids], c2w, intr), axis=1)
    assert np.median(err) < 0.05 and err.max() < 0.2
