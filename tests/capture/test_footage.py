"""Footage sources: videos (times, rotation, truncation), image and RAW folders, Record3D exports."""

from __future__ import annotations

import json
import zipfile
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from dbb_capture.cli.capture import main

from dbb_capture.capture.footage import (
    FootageFrame,
    ImageFolderSource,
    R3dSource,
    RawFolderSource,
    VideoSource,
    blurry_mask,
    open_footage,
    sample_indices,
    sharpness,
)
from dbb_capture.core.errors import DbbError, InputError


def _frame(i: int, w: int = 64, h: int = 48) -> np.ndarray:
    """Grey level encodes the frame number; a white block marks the top-left corner."""
    img = np.full((h, w, 3), 20 + 10 * i, np.uint8)
    img[:12, :16] = 255
    return img


def _write_video(path: Path, n: int, fps: int = 10, rotation: int | None = None) -> None:
    import av

    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=Fraction(fps))
        s.width, s.height, s.pix_fmt = 64, 48, "yuv420p"
        s.options = {"crf": "10", "g": "4"}
        if rotation is not None:
            s.set_display_rotation(rotation)
        for i in range(n):
            for p in s.encode(av.VideoFrame.from_ndarray(_frame(i), format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)


def test_video_times_and_subsets(tmp_path):
    _write_video(tmp_path / "v.mp4", 12)
    src = open_footage(tmp_path / "v.mp4")
    assert isinstance(src, VideoSource)
    info = src.info
    assert (info.width, info.height, info.n_frames) == (64, 48, 12)
    np.testing.assert_allclose(info.times, np.arange(12) / 10, atol=1e-6)
    # A subset after a seek returns exactly those frames, identified by their grey level.
    got = list(src.read([9, 3, 10], gray=False))
    assert [f.index for f in got] == [3, 9, 10]
    for f in got:
        assert f.time == pytest.approx(f.index / 10)
        assert abs(int(np.median(f.image[30:, 30:, 1])) - (20 + 10 * f.index)) <= 3
    g = next(src.read([5], gray=True))
    assert g.image.shape == (48, 64) and g.image.dtype == np.uint8


def test_video_rotation_metadata_is_applied(tmp_path):
    _write_video(tmp_path / "r.mp4", 3, rotation=90)
    src = VideoSource(tmp_path / "r.mp4")
    assert (src.info.width, src.info.height) == (48, 64)
    img = next(src.read([0])).image
    assert img.shape == (64, 48, 3)
    # 90 degrees counter-clockwise: the stored top-left block is now bottom-left.
    assert img[-6, 4, 0] > 200 and img[4, 4, 0] < 100 and img[-6, -4, 0] < 100


def test_image_folder_and_sampling(tmp_path):
    for i in range(6):
        cv2.imwrite(str(tmp_path / f"f{i:02d}.png"), _frame(i))
    src = open_footage(tmp_path)
    assert isinstance(src, ImageFolderSource) and src.info.n_frames == 6
    frames = list(src.read([0, 4], gray=True))
    assert [f.name for f in frames] == ["f00", "f04"]
    assert frames[1].image.shape == (48, 64)
    cv2.imwrite(str(tmp_path / "f99.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(InputError, match="differs"):
        list(ImageFolderSource(tmp_path).read([6]))


def test_sample_indices():
    t = np.arange(90) / 30.0
    np.testing.assert_array_equal(sample_indices(t, 10), np.arange(0, 90, 3))
    np.testing.assert_array_equal(sample_indices(t, None), np.arange(90))
    assert len(sample_indices(t, 1)) == 3
    assert len(sample_indices(t, 1000)) == 90  # never more frames than there are
    with pytest.raises(DbbError):
        sample_indices(t, -1)


def test_sharpness_flags_blurred_frames():
    rng = np.random.default_rng(0)
    sharp = (rng.random((120, 160)) * 255).astype(np.uint8)
    scores = []
    for i in range(10):
        img = cv2.GaussianBlur(sharp, (0, 0), 3) if i in (4, 7) else sharp
        scores.append(sharpness(img))
    np.testing.assert_array_equal(np.flatnonzero(blurry_mask(np.array(scores))), [4, 7])
    assert not blurry_mask(np.array(scores), ratio=0).any()


def test_record3d_export(tmp_path):
    K = np.array([[500.0, 0, 100], [0, 510.0, 80], [0, 0, 1]])
    meta = {"w": 200, "h": 160, "fps": 30, "K": K.T.ravel().tolist(),
            "poses": [[0, 0, 0, 1, 0.1, 0.2, 0.3], [0, 0, 0.7071068, 0.7071068, 0, 0, 0]]}
    path = tmp_path / "cap.r3d"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("metadata", json.dumps(meta))
        for i in range(2):
            ok, buf = cv2.imencode(".jpg", cv2.resize(_frame(i), (200, 160)))
            z.writestr(f"rgbd/{i}.jpg", buf.tobytes())
    src = open_footage(path)
    assert isinstance(src, R3dSource) and src.info.n_frames == 2 and src.info.fps == 30
    intr = src.intrinsics()
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == (500.0, 510.0, 100.0, 80.0)  # column-major K read right
    c2w = src.arkit_c2w_opencv()
    np.testing.assert_allclose(c2w[0, :3, 3], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(c2w[0, :3, :3], np.diag([1.0, -1, -1]), atol=1e-9)  # OpenGL -> OpenCV axes
    assert [f.index for f in src.read([1])] == [1]


def test_raw_folder_reports_undecodable_files(tmp_path):
    (tmp_path / "a.dng").write_bytes(b"not a raw file")
    src = open_footage(tmp_path)
    assert isinstance(src, RawFolderSource)
    with pytest.raises(InputError, match="cannot decode RAW"):
        src.info


@pytest.mark.parametrize("make", ["garbage", "missing"])
def test_cli_unreadable_footage_exits_2(tmp_path, make):
    (tmp_path / "board.json").write_text(json.dumps(
        {"squares_x": 5, "squares_y": 7, "square_length": 0.04, "marker_length": 0.02,
         "dictionary": "DICT_6X6_250"}))
    if make == "garbage":
        (tmp_path / "video.mp4").write_bytes(b"\x00" * 1000)
    res = CliRunner().invoke(main, ["calibrate", str(tmp_path), "-o", str(tmp_path / "cam.json")])
    assert res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and ("cannot read video" in lines[0] or "no footage" in lines[0])


def test_prefetched_keeps_order_and_raises_decoder_errors():
    from dbb_capture.capture.footage import prefetched

    def gen():
        for i in range(10):
            yield FootageFrame(i, i / 10, np.zeros((2, 2), np.uint8), str(i))
        raise InputError("broken at 10")

    got = []
    with pytest.raises(InputError, match="broken"):
        for f in prefetched(gen(), depth=2):
            got.append(f.index)
    assert got == list(range(10))
