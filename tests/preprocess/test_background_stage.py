"""The background stage: the object's sphere checked against the views; no clean plate."""

from __future__ import annotations

import json

import cv2
import pytest
from click.testing import CliRunner
from dbb_capture.cli.capture import main


@pytest.mark.parametrize("center, words", [([5.0, 5.0, -1.0], "from the board centre"),   # checked first
                                             ([1.9, 0.1, -0.1], "outside the view")])      # needs the poses
def test_object_sphere_outside_the_views_is_an_error(plate_capture, tmp_path, center, words):
    bad = tmp_path / "object.json"
    bad.write_text(json.dumps({"center": center, "radius": 0.1}))
    res = CliRunner().invoke(main, ["preprocess", str(plate_capture), "-o", str(tmp_path / "ds"),
                                    "--object", str(bad), "--camera",
                                    str(plate_capture / "ground_truth" / "camera.json")])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1 and words in lines[0], res.output
    assert not (tmp_path / "ds").exists()


def test_preprocess_without_plate_trains_the_field_again_on_the_mattes_room(plate_capture, tmp_path):
    ds = tmp_path / "ds"
    res = CliRunner().invoke(main, ["preprocess", str(plate_capture), "-o", str(ds), "--background-minutes", "0.05",
                                    "--camera", str(plate_capture / "ground_truth" / "camera.json"),
                                    "--crop-size", "48", "--sequence-length", "4", "--no-clean-plate"])
    assert res.exit_code == 0, res.output
    rep = json.loads((ds / "background" / "report.json").read_text())
    assert rep["mode"].startswith("object video") and rep["refined_on_room"]["steps"] > 0
    from dbb_capture.background.model import BackgroundModel

    assert BackgroundModel.load(ds / "background" / "field.pt").refine.steps == rep["refined_on_room"]["steps"]
    fr = json.loads((ds / "crops.json").read_text())["frames"][0]
    rgba = cv2.imread(str(ds / fr["file_path"]), cv2.IMREAD_UNCHANGED)
    assert rgba[..., 3].max() == 255 and rgba[0, 0, 3] == 0
    assert not (ds / "matte_scratch").exists()
