"""Fuzz: a capture's inputs (video, frames/, board.json, object.json, camera.json) corrupted,
given to ``dbb-capture preprocess --stop-after poses``: one line and exit 2, before the poses
are solved, or (where going on is right) a warning and a dataset."""

from __future__ import annotations

import json

import pytest
from fuzz.conftest import PREPROCESS, capture_copy, check, invoke, out_path
from fuzz.mutate import Case, byte_cases, json_cases

SEED = 43


def _video_may_pass(cid: str) -> bool:
    # Flipped bytes inside the coded frames decode to damaged pictures (FFmpeg conceals them),
    # and many in the container's index change nothing FFmpeg needs.
    return cid.startswith("flip-")


VIDEO = byte_cases(SEED, may_pass=_video_may_pass)
# Faststart (the index first, as phones and uploads write it): a cut file still opens and
# announces every frame; from half of them on it goes on with a warning.
FASTSTART = byte_cases(SEED + 100, truncate_at=(0.3, 0.45, 0.6, 0.8, 0.95), flips=((2, "head"), (8, "middle")),
                       may_pass=lambda cid: _video_may_pass(cid) or cid in ("truncate-60pct", "truncate-80pct",
                                                                             "truncate-95pct"))


def _preprocess(capfd, tmp_path, cap, *flags):
    out = out_path(tmp_path, "ds")
    return out, invoke(capfd, "dbb-capture", "preprocess", cap, "-o", out, *PREPROCESS, *flags)


@pytest.mark.parametrize("case", VIDEO, ids=lambda c: c.id)
def test_video(capfd, tmp_path, capture_base, case: Case):
    cap = capture_copy(capture_base, tmp_path)
    case.apply(cap / "video.mp4")
    out, res = _preprocess(capfd, tmp_path, cap)
    check(res, out, case.may_pass)


@pytest.mark.parametrize("case", FASTSTART, ids=lambda c: c.id)
def test_video_faststart(capfd, tmp_path, capture_base, case: Case):
    cap = capture_copy(capture_base, tmp_path, "faststart")
    case.apply(cap / "video.mp4")
    out, res = _preprocess(capfd, tmp_path, cap)
    cut = case.id.startswith("truncate-")
    check(res, out, case.may_pass, warning="frames" if cut else None)
    if cut and res.code == 0:
        record = json.loads((out / "preprocess.json").read_text())
        assert any("announces" in w for w in record["warnings"]), record


def _frames_cases() -> list[Case]:
    cases = byte_cases(SEED + 200, truncate_at=(0.0, 0.1, 0.5, 0.9), flips=((1, "head"), (8, "middle"), (4, "tail")))

    def other_size(path):
        import cv2
        import numpy as np
        cv2.imwrite(str(path), np.zeros((100, 60, 3), np.uint8))

    def text(path):
        path.write_text("not an image [v2]\n")

    def grey16(path):
        import cv2
        import numpy as np
        cv2.imwrite(str(path), np.full((240, 320), 30000, np.uint16))

    cases += [Case("other-size", other_size), Case("text-as-png", text), Case("grey-16-bit", grey16, may_pass=True)]
    return cases


FRAMES = _frames_cases()


@pytest.mark.parametrize("case", FRAMES, ids=lambda c: c.id)
def test_frames(capfd, tmp_path, capture_base, case: Case):
    cap = capture_copy(capture_base, tmp_path, "frames")
    case.apply(sorted((cap / "frames").iterdir())[4])
    out, res = _preprocess(capfd, tmp_path, cap)
    # A damaged tail (PNG's end chunk) may leave the picture whole.
    check(res, out, case.may_pass or case.id.startswith("flip-4-tail") or case.id == "truncate-90pct")


def test_frames_empty_folder(capfd, tmp_path, capture_base):
    cap = capture_copy(capture_base, tmp_path, "frames")
    for p in (cap / "frames").iterdir():
        p.unlink()
    out, res = _preprocess(capfd, tmp_path, cap)
    check(res, out)


BOARD_CASES = json_cases(
    numbers=[("squares_x",), ("squares_y",), ("square_length",), ("marker_length",)],
    others=[("dictionary",), ("legacy_pattern",)],
    # legacy_pattern may be left out (false); a bool where a number goes is refused as a type.
    skip=lambda cid: cid == "missing-legacy_pattern", may_pass=lambda cid: cid == "extra-key",
) + byte_cases(SEED + 300, truncate_at=(0.0, 0.5, 0.9), flips=((1, "head"), (3, "any")),
               may_pass=lambda cid: cid.startswith("flip-"))   # a flipped digit may still be a board


def _json_case(capfd, tmp_path, capture_base, name: str, case: Case, via_flag: str | None = None):
    cap = capture_copy(capture_base, tmp_path)
    target = cap / name
    if via_flag:                 # the file given by a flag instead, from a folder of its own
        target = cap.parent / "given [flag]" / name
        target.parent.mkdir()
        (cap / name).rename(target)
    case.apply(target)
    out, res = _preprocess(capfd, tmp_path, cap, *((via_flag, target) if via_flag else ()))
    check(res, out, case.may_pass)
    return res


@pytest.mark.parametrize("case", BOARD_CASES, ids=lambda c: c.id)
def test_board_json(capfd, tmp_path, capture_base, case: Case):
    res = _json_case(capfd, tmp_path, capture_base, "board.json", case)
    if case.id in ("negative-square_length", "zero-square_length"):
        assert "square_length" in res.lines[0] and "marker_length" not in res.lines[0].split(":")[-1], res.lines


def _far(path):
    path.write_text(json.dumps({"center": [10, 10, 10], "radius": 0.1}))


OBJECT_CASES = json_cases(
    numbers=[("radius",)], arrays=[(("center",), 3)], others=[("kind",)],
    # kind is optional (only dbb-batch reads it)
    skip=lambda cid: cid in ("missing-kind", "null-kind"), may_pass=lambda cid: cid == "extra-key",
) + [Case("centre-far-from-board", _far)] + byte_cases(SEED + 400, truncate_at=(0.0, 0.5), flips=((2, "head"),),
                                                        may_pass=lambda cid: cid.startswith("flip-"))


@pytest.mark.parametrize("case", OBJECT_CASES, ids=lambda c: c.id)
def test_object_json(capfd, tmp_path, capture_base, case: Case):
    res = _json_case(capfd, tmp_path, capture_base, "object.json", case, via_flag="--object")
    if res.code == 2 and case.id.startswith(("document-", "missing-", "number-center", "nested-center")):
        assert '"center": [x, y, z]' in res.lines[0], res.lines[0]


CAMERA_CASES = json_cases(
    numbers=[("width",), ("height",), ("fx",), ("fy",), ("cx",)], arrays=[(("dist",), 5)],
    # a shorter distortion list is the first terms (OpenCV's 4-term model), zero terms are none
    skip=lambda cid: cid in ("missing-dist",),
    may_pass=lambda cid: cid in ("extra-key", "short-dist", "zero-dist"),
) + byte_cases(SEED + 500, truncate_at=(0.0, 0.5), flips=((2, "head"),), may_pass=lambda cid: cid.startswith("flip-"))


@pytest.mark.parametrize("case", CAMERA_CASES, ids=lambda c: c.id)
def test_camera_json(capfd, tmp_path, capture_base, case: Case):
    _json_case(capfd, tmp_path, capture_base, "camera.json", case, via_flag="--camera")
