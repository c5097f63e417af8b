"""Which folders are captures, and their kind (object.json's, else the default)."""

from __future__ import annotations

import json

import pytest

from dbb_capture.batch.captures import find_captures
from dbb_capture.capture.object_spec import object_kind
from dbb_capture.core.errors import DbbError


def _capture(folder, obj=None, footage="video.mp4"):
    folder.mkdir(parents=True)
    (folder / footage).write_bytes(b"")
    if obj is not None:
        (folder / "object.json").write_text(json.dumps(obj))
    return folder


def test_kinds_and_what_is_not_a_capture(tmp_path):
    root = tmp_path / "caps"
    _capture(root / "a", {"center": [0, 0, 0], "radius": 0.1, "kind": "dynamic"})
    _capture(root / "b", {"center": [0, 0, 0], "radius": 0.1})
    _capture(root / "c", {"center": [0, 0, 0], "radius": 0.1, "kind": "wobbly"})
    _capture(root / "d", footage="scan.r3d")
    (root / "notes").mkdir()
    (root / ".hidden").mkdir()
    _capture(root / "out")                      # the batch's own output inside CAPTURES_DIR
    jobs, others = find_captures(root, root / "out", "static")
    by = {j.name: j for j in jobs}
    assert sorted(by) == ["a", "b", "c", "d"] and others == ["notes"]
    assert (by["a"].kind, by["a"].kind_source) == ("dynamic", "object.json")
    assert (by["b"].kind, by["b"].kind_source) == ("static", "default")
    assert by["c"].kind is None and "wobbly" in by["c"].problem
    assert by["a"].paths.bundle == root / "out" / "a" / "bundle"


def test_no_captures_is_one_clear_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DbbError, match="no captures in"):
        find_captures(tmp_path / "empty", tmp_path / "out", "static")
    with pytest.raises(DbbError, match="captures folder not found"):
        find_captures(tmp_path / "nope", tmp_path / "out", "static")


def test_object_kind(tmp_path):
    p = tmp_path / "object.json"
    assert object_kind(p) is None
    p.write_text('{"center": [0, 0, 0], "radius": 1, "kind": "static"}')
    assert object_kind(p) == "static"
    p.write_text("[1, 2]")
    with pytest.raises(DbbError, match="JSON object"):
        object_kind(p)
