"""The crops stage: the dataset it writes, and the second matte pass across segment cuts."""

from __future__ import annotations

import json

import cv2
import numpy as np
from click.testing import CliRunner
from conftest import UP, ring_cameras, small_intrinsics
from dbb_capture.cli.capture import main

from dbb_capture.core.images import LABEL_PX
from dbb_capture.crops.camera import crop_camera


def test_preprocess_writes_crops_dataset(plate_capture, tmp_path):
    ds = tmp_path / "ds"
    res = CliRunner().invoke(main, ["preprocess", str(plate_capture), "-o", str(ds), "--background-minutes", "0.05",
                                    "--camera", str(plate_capture / "ground_truth" / "camera.json"),
                                    "--crop-size", "48", "--sequence-length", "4"])
    assert res.exit_code == 0, res.output
    crops = json.loads((ds / "crops.json").read_text())
    assert crops["crop_size"] == 48 and crops["up"] == [0.0, 0.0, -1.0]
    fr = crops["frames"][0]
    for key in ("file_path", "transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h", "source_frame", "time",
                "viewpoint", "split"):
        assert key in fr
    assert set(fr["viewpoint"]) == {"azimuth_deg", "elevation_deg", "distance_m"}
    assert {f["split"] for f in crops["frames"]} == {"train", "test"}
    rgba = cv2.imread(str(ds / fr["file_path"]), cv2.IMREAD_UNCHANGED)
    assert rgba.shape == (48, 48, 4) and rgba[..., 3].max() == 255 and rgba[0, 0, 3] == 0
    tf = json.loads((ds / "transforms.json").read_text())
    mask = cv2.imread(str(ds / tf["frames"][0]["mask_path"]), cv2.IMREAD_GRAYSCALE)
    assert mask.shape == (240, 320) and 0 < (mask > 127).mean() < 0.5
    stats = json.loads((ds / "dataset.json").read_text())
    assert stats["crops"] == len(crops["frames"]) == stats["frames_posed"] >= 6
    assert stats["background"]["mode"] == "clean plate"
    assert json.loads((ds / "background" / "report.json").read_text())["train_px"] >= 64
    assert stats["sequences"]["train"] > 0
    assert (ds / "contact_sheet.png").stat().st_size > 10_000 and (ds / "background" / "field.pt").is_file()
    # The sheet names its columns (a band on top) and each row's frame (a column on the left).
    sheet = cv2.imread(str(ds / "contact_sheet.png"))
    band, names = sheet[:LABEL_PX], sheet[LABEL_PX:, :90]
    x = np.cumsum([90, sheet.shape[1] - 90 - 5 * 128] + [128] * 5)
    assert all((band[:, a + 2:b - 2] > 200).any() for a, b in zip(x[:-1], x[1:]))      # text in every column
    assert all((names[i * 128:(i + 1) * 128] > 200).any() for i in range((sheet.shape[0] - LABEL_PX) // 128))
    assert not (ds / "matte_scratch").exists()          # the matte's second pass cleans up after itself
    assert json.loads((ds / "preprocess.json").read_text())["stages_run"] == ["poses", "background", "crops"]


def test_second_matte_pass_votes_across_segment_cuts(tmp_path):
    """The crops stage's second pass gives the same crops in one segment or in three (each sees its
    neighbours across the cut), and the temporal median skips a gap in time."""
    from dbb_capture.crops.matte import CaptureMatte, MatteConfig
    from dbb_capture.preprocess.crop_stage import (
        _FirstMatte,
        _matte_segment,
        _MatteSegment,
    )

    center = np.array([0.3, 0.2, -0.08])
    c2ws = ring_cameras(center, n=8)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:32, 0:32]
    room = np.where((np.sin(yy / 2.0) > 0)[..., None], [150, 90, 50], [95, 55, 35]).astype(float)
    noisy = lambda im: np.clip(im + rng.normal(0, 2.0, im.shape), 0, 255).astype(np.uint8)
    crops, c2w = [], {}
    for i, m in enumerate(c2ws):
        disc = (xx - 16) ** 2 + (yy - 15) ** 2 <= (7 if i != 4 else 3) ** 2   # frame 4 misses most of it
        obs = noisy(np.where(disc[..., None], [40, 70, 200], room))
        np.savez(tmp_path / f"{i:05d}.npz", observed=obs, predicted=noisy(room), guessed=np.zeros(0, bool),
                 inside=np.zeros(0, np.uint8))
        crops.append(_FirstMatte(i, f"{i:05d}", crop_camera(m, small_intrinsics(), center, 0.1, UP, 32, 0.9), False, 0.01))
        c2w[i] = m
    follows = frozenset({1, 2, 4, 5, 6, 7})                 # frame 3 follows a gap

    def run(parts, out):
        (out / "crops").mkdir(parents=True)
        (out / "masks").mkdir()
        for a, b in parts:
            seg = _MatteSegment(tuple(crops[a:b]), crops[a - 1] if a else None, crops[b] if b < 8 else None,
                                follows, c2w, small_intrinsics(), 0.9, MatteConfig(), CaptureMatte(0.01), tmp_path, out,
                                frozenset())
            _matte_segment(seg, tick=lambda n: None)
        return [cv2.imread(str(out / "crops" / f"{i:05d}.png"), cv2.IMREAD_UNCHANGED) for i in range(8)]

    one = run([(0, 8)], tmp_path / "one")
    three = run([(0, 3), (3, 5), (5, 8)], tmp_path / "three")
    assert all(np.array_equal(a, b) for a, b in zip(one, three))
    big = (xx - 16) ** 2 + (yy - 15) ** 2 <= 6 ** 2
    assert (one[4][..., 3][big] > 127).mean() > 0.95      # outvoted by frames 3 and 5
    assert (one[2][..., 3][big] > 127).mean() > 0.95
