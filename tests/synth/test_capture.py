"""Writing a synthetic capture folder."""

from __future__ import annotations

import json

import cv2
import numpy as np

from dbb_capture.capture.board import BoardSpec
from dbb_capture.geometry.conventions import opencv_from_opengl
from dbb_capture.synth.capture import load_ground_truth
from dbb_capture.synth.render import render_object_rgba
from dbb_capture.synth.scene import SynthConfig


def test_written_capture_is_consistent(tiny_dynamic_capture):
    import av

    cap = tiny_dynamic_capture
    intr, cams, model = load_ground_truth(cap)
    board = BoardSpec.load(cap / "board.json")
    sphere = json.loads((cap / "object.json").read_text())
    frames = cams["video"]
    assert len(frames) == 15 and cams["background"] == []
    assert not (cap / "background.mp4").exists()
    with av.open(str(cap / "video.mp4")) as c:
        decoded = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(decoded) == len(frames) and decoded[0].shape == (240, 320, 3)
    assert np.allclose(np.diff([f["time"] for f in frames]), 0.2)
    # The bounding sphere holds every ellipsoid at every frame time.
    c, rad = np.array(sphere["center"]), sphere["radius"]
    u = np.random.default_rng(0).standard_normal((500, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    for f in frames:
        for ce, R, e in model.posed(f["time"]):
            surface = ce + (u * np.asarray(e.radii)) @ R.T
            assert np.linalg.norm(surface - c, axis=1).max() <= rad + 1e-6
    # Ground-truth RGBA renders agree with the stored masks, and the decoded video shows the
    # object where the mask says (object pixels differ from the clean-plate-free board region).
    ious = []
    for i in (0, 7, 14):
        c2w = opencv_from_opengl(np.array(frames[i]["transform_matrix"]))
        rgba = render_object_rgba(model, intr, c2w, frames[i]["time"], samples=2)
        mask = cv2.imread(str(cap / "ground_truth" / "masks" / f"{i:05d}.png"), cv2.IMREAD_UNCHANGED)
        a, m = rgba[..., 3] >= 128, mask >= 128
        ious.append((a & m).sum() / max((a | m).sum(), 1))
        assert np.abs(decoded[i][m].astype(int) - rgba[m][:, :3].astype(int)).mean() < 12
    assert min(ious) > 0.99
    assert board.dictionary == "DICT_5X5_100"


def test_clean_plate_has_no_object(tiny_static_capture):
    import av

    cap = tiny_static_capture
    _, cams, _ = load_ground_truth(cap)
    assert len(cams["background"]) == 5
    with av.open(str(cap / "background.mp4")) as c:
        n = sum(1 for _ in c.decode(video=0))
    assert n == 5
    # The clean plate's path differs from the object video's.
    a = np.array(cams["video"][0]["transform_matrix"])
    b = np.array(cams["background"][0]["transform_matrix"])
    assert np.linalg.norm(a[:3, 3] - b[:3, 3]) > 0.01


def test_worker_processes_render_the_same_capture(tmp_path):
    import av

    from dbb_capture.synth.capture import write_capture

    outs = []
    for workers in (1, 2):
        cfg = SynthConfig(kind="dynamic", seconds=0.8, fps=5, width=160, height=120,
                          background_seconds=0.4, seed=9, workers=workers)
        write_capture(cfg, tmp_path / f"w{workers}")
        with av.open(str(tmp_path / f"w{workers}" / "video.mp4")) as c:
            outs.append(np.stack([f.to_ndarray(format="rgb24") for f in c.decode(video=0)]))
        masks = sorted((tmp_path / f"w{workers}" / "ground_truth" / "masks").iterdir())
        outs.append(np.stack([cv2.imread(str(m), cv2.IMREAD_UNCHANGED) for m in masks]))
    assert outs[0].shape == (4, 120, 160, 3)
    assert np.array_equal(outs[0], outs[2]) and np.array_equal(outs[1], outs[3])
