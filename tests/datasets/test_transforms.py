"""Reading and writing transforms-style files: nerfstudio, Blender, crops.json."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from conftest import shared_data

from dbb_capture.core.errors import DbbError
from dbb_capture.datasets.images import load_rgba
from dbb_capture.datasets.records import (
    Frame,
    ObjectVolume,
    estimate_volume,
    holdout_every,
)
from dbb_capture.datasets.transforms import (
    intrinsics_fields,
    load_dataset,
    write_crops,
    write_transforms,
)
from dbb_capture.geometry.cameras import Intrinsics
from dbb_capture.geometry.conventions import opengl_from_opencv

from .conftest import INTR, poses_around, write_image


def test_transforms_json_conventions_paths_and_per_frame_intrinsics(tmp_path):
    poses = poses_around()
    (tmp_path / "img").mkdir()
    frames = []
    for i, c2w in enumerate(poses):
        write_image(tmp_path / "img" / f"{i}.jpg", rgba=False)
        frames.append({"file_path": f"img/{i}.jpg", "transform_matrix": opengl_from_opencv(c2w).tolist()})
    frames[2]["file_path"] = str((tmp_path / "img" / "2.jpg").resolve())       # absolute path
    frames[3].update({"fl_x": 61.0, "fl_y": 62.0, "cx": 20.0, "cy": 15.0})       # per-frame, corner origin
    meta = {**intrinsics_fields(INTR), "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    ds = load_dataset(tmp_path)
    assert ds.kind == "transforms" and not ds.rgba and len(ds.frames) == 4
    for f, c2w in zip(ds.frames, poses):
        np.testing.assert_allclose(f.c2w, c2w, atol=1e-12)        # OpenGL in the file, OpenCV inside
    assert ds.frames[0].intr == INTR                              # distortion honoured
    assert ds.frames[2].image_path.is_absolute() and ds.frames[2].image_path.exists()
    i3 = ds.frames[3].intr
    assert (i3.fx, i3.fy, i3.cx, i3.cy, i3.dist) == (61.0, 62.0, 19.5, 14.5, INTR.dist)    # OpenCV centres inside


def test_blender_camera_angle_and_extensionless_paths(tmp_path):
    (tmp_path / "train").mkdir()
    frames = []
    for i, c2w in enumerate(poses_around(3)):
        write_image(tmp_path / "train" / f"r_{i}.png")
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": opengl_from_opencv(c2w).tolist()})
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    ds = load_dataset(tmp_path)
    f = ds.frames[0]
    assert ds.kind == "blender" and ds.rgba
    assert f.intr.fx == pytest.approx(20 / math.tan(0.35)) and f.intr.fy == f.intr.fx
    assert (f.intr.cx, f.intr.cy) == (19.5, 14.5)                 # image centre, OpenCV pixel centres
    rgba = load_rgba(f)
    assert rgba.shape == (30, 40, 4) and rgba[0, 0, 3] == 0 and rgba[-1, 0, 3] == 1


def test_crops_json_split_volume_and_write_round_trip(tmp_path):
    frames = []
    for i, c2w in enumerate(poses_around(4)):
        write_image(tmp_path / f"{i:05d}.png")
        frames.append(Frame(f"{i:05d}", tmp_path / f"{i:05d}.png", c2w, INTR, "test" if i == 1 else "train",
                            time=0.1 * i))
    write_transforms(tmp_path / "crops.json", frames, ObjectVolume((0.1, 0.2, 0.3), 0.4))
    ds = load_dataset(tmp_path)
    assert ds.kind == "crops" and ds.rgba
    assert [f.split for f in ds.frames] == ["train", "test", "train", "train"]
    assert ds.volume == ObjectVolume((0.1, 0.2, 0.3), 0.4)
    assert ds.frames[2].time == pytest.approx(0.2)
    np.testing.assert_allclose(ds.frames[3].c2w, frames[3].c2w, atol=1e-9)     # written to 9 decimals
    assert [f.split for f in holdout_every(ds.frames, 2)] == ["test", "train", "test", "train"]


def test_crops_json_names_each_crops_camera_source_and_predicted_room(tmp_path):
    """crops.json keeps each crop's own camera, where it came from and what its matte was cut from
    (training composites over that room), and says nothing of such files for a crop that has none
    (one past the frame's border)."""
    from dbb_capture.geometry.viewpoint import Viewpoint

    crop = Intrinsics(32, 32, 40.0, 40.0, 15.5, 15.5)
    frames = []
    for i, c2w in enumerate(poses_around(3)):
        for sub in ("crops", "crops_observed", "crops_background"):
            (tmp_path / sub).mkdir(exist_ok=True)
            cv2.imwrite(str(tmp_path / sub / f"{i:05d}.png"), np.full((32, 32, 4), 200, np.uint8))
        room = i != 2
        frames.append(Frame(f"{i:05d}", tmp_path / "crops" / f"{i:05d}.png", c2w, replace(crop, fx=40.0 + i),
                            "test" if i == 2 else "train", time=0.1 * i,
                            observed_path=tmp_path / "crops_observed" / f"{i:05d}.png" if room else None,
                            background_path=tmp_path / "crops_background" / f"{i:05d}.png" if room else None,
                            source_frame=10 + i, viewpoint=Viewpoint(30.0 * i, 20.0, 0.5), touches_border=not room))
    write_crops(tmp_path / "crops.json", frames, np.array([0.1, 0.2, 0.3]), 0.4, np.array([0.0, 0.0, -1.0]), 32, 0.9,
                2, [(0, "train")])
    doc = json.loads((tmp_path / "crops.json").read_text())
    assert doc["frames"][0]["observed_path"] == "crops_observed/00000.png"
    assert doc["frames"][0]["background_path"] == "crops_background/00000.png"
    assert "observed_path" not in doc["frames"][2] and doc["frames"][2]["touches_border"] is True
    assert "fl_x" not in doc and doc["w"] == 32 and doc["sequences"] == [{"start": 0, "split": "train"}]
    ds = load_dataset(tmp_path)
    assert [f.intr.fx for f in ds.frames] == [40.0, 41.0, 42.0]
    assert [f.source_frame for f in ds.frames] == [10, 11, 12]
    assert ds.frames[1].viewpoint == Viewpoint(30.0, 20.0, 0.5) and ds.frames[2].touches_border
    assert ds.frames[0].observed_path == tmp_path / "crops_observed" / "00000.png" and ds.frames[2].observed_path is None
    assert ds.volume == ObjectVolume((0.1, 0.2, 0.3), 0.4)


def test_bad_datasets_fail_clearly(tmp_path):
    with pytest.raises(DbbError, match="none of"):
        load_dataset(tmp_path)
    (tmp_path / "transforms.json").write_text(json.dumps(
        {**intrinsics_fields(INTR), "frames": [{"file_path": "nope.png", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(DbbError, match="image not found"):
        load_dataset(tmp_path)


def test_real_datasets_load():
    lego = load_dataset(shared_data("nerf_lego"))
    assert lego.kind == "blender" and len(lego.frames) == 100 and lego.frames[0].intr.fx == pytest.approx(1111.111, abs=1e-3)
    fox = load_dataset(shared_data("fox"))
    assert fox.kind == "transforms" and not fox.rgba and fox.frames[0].intr.dist[0] == pytest.approx(0.0578421)
    # instant-ngp cameras look at the figurine: the estimated centre lies in front of all of them.
    v = estimate_volume(fox.frames)
    assert all((np.asarray(v.center) - f.c2w[:3, 3]) @ f.c2w[:3, 2] > 0 for f in fox.frames)


def test_files_put_the_pixel_origin_at_the_corner_and_old_crops_are_refused(tmp_path):
    """The contract's convention: a centred 64 px crop has cx = 32 in the file (nerfstudio's and
    instant-ngp's origin), 31.5 inside (OpenCV's pixel centres); a crops.json of the older
    convention is refused rather than read half a pixel off."""
    crop = Intrinsics(64, 64, 80.0, 80.0, 31.5, 31.5)
    (tmp_path / "crops").mkdir()
    cv2.imwrite(str(tmp_path / "crops" / "0.png"), np.full((64, 64, 4), 200, np.uint8))
    f = Frame("0", tmp_path / "crops" / "0.png", poses_around(1)[0], crop, time=0.0)
    write_crops(tmp_path / "crops.json", [f], np.zeros(3), 0.1, np.array([0.0, 0.0, -1.0]), 64, 0.9, 2, [])
    doc = json.loads((tmp_path / "crops.json").read_text())
    assert (doc["frames"][0]["cx"], doc["frames"][0]["cy"]) == (32.0, 32.0)
    assert doc["applied_transform"] == [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0]]
    assert load_dataset(tmp_path).frames[0].intr == crop
    del doc["dbb_dataset_version"]
    (tmp_path / "crops.json").write_text(json.dumps(doc))
    with pytest.raises(DbbError, match="older version"):
        load_dataset(tmp_path)


def _one_frame_dataset(tmp_path, **top) -> dict:
    write_image(tmp_path / "0.png")
    doc = {**intrinsics_fields(INTR), **top,
           "frames": [{"file_path": "0.png", "transform_matrix": opengl_from_opencv(poses_around(1)[0]).tolist()}]}
    return doc


@pytest.mark.parametrize("edit, words", [
    (lambda d: d["frames"][0].update(transform_matrix=np.diag([2.0, 2, 2, 1]).tolist()), "frames[0].transform_matrix must be a camera pose"),
    (lambda d: d["frames"][0].update(transform_matrix=np.diag([1.0, 1, -1, 1]).tolist()), "with a mirror"),
    (lambda d: d["frames"][0]["transform_matrix"][3].__setitem__(0, 0.5), "must end with the row [0, 0, 0, 1]"),
    (lambda d: d["frames"][0]["transform_matrix"][1].__setitem__(2, float("nan")), "transform_matrix[1][2] must be a finite"),
    (lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(3, 1e9), "more than 1e+06 from the origin"),
    (lambda d: d.pop("w"), "transforms.json: w is missing"),
    (lambda d: d.update(fl_x=float("inf")), "fl_x must be a finite number"),
    (lambda d: d["frames"][0].update(fl_x=-3), "frames[0].fl_x -3 px must be at least"),
    (lambda d: d["frames"][0].update(time=-1), "frames[0].time -1 s must be at least 0"),
    (lambda d: d["frames"][0].update(split=7), "frames[0].split must be a string"),
    (lambda d: d.update(up=[0, 0, 0]), "up [0.0, 0.0, 0.0] must be a direction"),
    (lambda d: d.update(object={"center": [0, 0, 0], "radius": 0}), "object.radius 0 must be above 0"),
    (lambda d: d.update(crop_size=32, dbb_dataset_version=3), "dbb_dataset_version 3 is newer"),
])
def test_each_bad_entry_is_named_with_what_it_must_be(tmp_path, edit, words):
    """A damaged or hand-edited entry is refused where the file is read, by name, before training."""
    doc = _one_frame_dataset(tmp_path)
    edit(doc)
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(DbbError) as e:
        load_dataset(tmp_path)
    assert words in str(e.value) and "transforms.json" in str(e.value)


def test_blender_files_take_the_image_size_and_rounded_poses_pass(tmp_path):
    """Without w and h the images give the size (Blender files); poses rounded to 4 digits are
    still rigid enough."""
    doc = _one_frame_dataset(tmp_path)
    del doc["w"], doc["h"]
    doc["frames"][0]["transform_matrix"] = np.round(doc["frames"][0]["transform_matrix"], 4).tolist()
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    f = load_dataset(tmp_path).frames[0]
    assert (f.intr.width, f.intr.height) == (40, 30)
