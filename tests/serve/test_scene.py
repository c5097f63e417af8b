"""Scene files and the protocol's records: validation, placements, round trips."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dbb_capture.core.errors import DbbError
from dbb_capture.serve.client import look_from
from dbb_capture.serve.protocol import REQUEST, FrameHeader, ProtocolError, ViewRequest, parse_control
from dbb_capture.serve.scene import load_scene, row_of


def test_scene_file_paths_placement_and_ids(tmp_path):
    (tmp_path / "scenes").mkdir()
    doc = {"objects": [{"bundle": "../b/toy.dbb", "position": [1, 2, 3], "yaw_deg": 90, "scale": 2},
                       {"bundle": "../b/toy.dbb"}, {"bundle": "/abs/mug", "id": "mug"}]}
    path = tmp_path / "scenes" / "scene.json"
    path.write_text(json.dumps(doc))
    a, b, c = load_scene(path)
    assert a.bundle == tmp_path / "scenes" / "../b/toy.dbb" and c.bundle.as_posix() == "/abs/mug"
    assert (a.id, b.id, c.id) == ("toy", "toy-2", "mug")
    # yaw 90 turns bundle +X to scene -Z (counter-clockwise seen from above), then scale, then move.
    p = a.scene_from_bundle @ [1, 0, 0, 1]
    assert np.allclose(p[:3], [1, 2, 3 - 2])


@pytest.mark.parametrize("doc, words", [
    ({}, "at least one object"),
    ({"objects": [{"position": [0, 0, 0]}]}, "needs \"bundle\""),
    ({"objects": [{"bundle": "a", "position": [0, 0]}]}, "position"),
    ({"objects": [{"bundle": "a", "position": [0, float("nan"), 0]}]}, "position"),
    ({"objects": [{"bundle": "a", "scale": 0}]}, "scale must be positive"),
    ({"objects": [{"bundle": "a", "colour": "red"}]}, "unknown field 'colour'"),
    ({"objects": [{"bundle": "a", "id": "x"}, {"bundle": "b", "id": "x"}]}, "two objects have the id"),
    ({"objects": [{"bundle": "a", "id": "../x"}]}, "id must be"),
])
def test_bad_scene_files_are_refused_by_name(tmp_path, doc, words):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(DbbError, match=words.replace("(", r"\(")):
        load_scene(path)


def test_bundles_without_a_scene_stand_in_a_row():
    row = row_of(["a", "b", "c"], [0.2, 0.4, 0.2])
    xs = [p.position[0] for p in row]
    assert xs == sorted(xs) and abs(sum(xs) - 0.0) < 1e-9 and [p.id for p in row] == ["a", "b", "c"]
    assert xs[1] - xs[0] == pytest.approx(0.1 + 0.3)


def test_request_and_frame_round_trip_and_checks():
    c2w = look_from([0.1, 0.4, 0.5], [0, 0, 0])
    r = ViewRequest(7, 123.5, 2, c2w, fov_y_deg=55, viewport_w=1280, viewport_h=720, size_px=0, eye=2,
                    lossless=True)
    data = r.pack()
    assert len(data) == REQUEST.size == 112
    back = ViewRequest.unpack(data)
    assert (back.seq, back.object, back.eye, back.lossless, back.size_px) == (7, 2, 2, True, 0)
    assert np.allclose(back.c2w, c2w, atol=1e-6)
    assert back.screen_size(0.2, 1.0) == pytest.approx(0.5 * 720 / np.tan(np.radians(27.5)) * 0.2)
    h = FrameHeader(7, 123.5, 2, 2, 1, 1e12, 3.5, c2w, np.array([0.1, 0.2, 0.3]), 0.25, 64, 64, 9, 100, 0)
    hb = FrameHeader.unpack(h.pack() + b"x" * 100)
    assert (hb.seq, hb.step, hb.width, hb.colour_bytes) == (7, 9, 64, 100)
    assert np.allclose(hb.canvas_centre, [0.1, 0.2, 0.3]) and hb.canvas_side_m == pytest.approx(0.25)
    flipped = c2w.copy()
    flipped[:3, 0] *= -1                                                    # a reflection
    with pytest.raises(ProtocolError, match="rigid"):
        ViewRequest.unpack(ViewRequest(1, 0, 0, flipped).pack())
    with pytest.raises(ProtocolError, match="viewport"):
        ViewRequest.unpack(ViewRequest(1, 0, 0, c2w, size_px=0).pack())


def test_control_messages():
    assert parse_control('{"type": "pause", "object": 1, "paused": false}').paused is False
    q = parse_control('{"type": "quality", "max_size": 256, "lossless": true}')
    assert (q.max_size, q.lossless, q.jpeg_quality, q.raw) == (256, True, None, None)
    assert parse_control('{"type": "quality", "raw": true}').raw is True
    for bad, code in (('{"type": "quality", "raw": 1}', "bad_value"), ('{"type": "pause", "paused": "yes"}', "bad_value"), ('[1, 2]', "bad_request"),
                      ('{"type": "reset", "object": true}', "bad_value"),
                      ('{"type": "quality", "jpeg_quality": 101}', "bad_value")):
        with pytest.raises(ProtocolError) as e:
            parse_control(bad)
        assert e.value.code == code
