"""Fuzz: the transforms-style files the trainers and the renderer read, corrupted: a dataset's
transforms.json (``dbb-train plenoctree``) and crops.json (``dbb-train rssm``), and a cameras
file given to ``dbb-export render``. One line and exit 2 before any training or rendering, no
output left."""

from __future__ import annotations

import json

import pytest
from fuzz.conftest import cameras_doc, check, copy_tree, invoke, odd_dir, out_path
from fuzz.mutate import Case, byte_cases, json_cases

SEED = 4300
SMALL_RSSM = ("--size", "32", "--batch", "2", "--set", "deter=16", "--set", "stoch=16", "--set", "hidden=64",
              "--set", "embed=64")

def _transforms_doc_cases() -> list[Case]:
    # Entries of tests/conftest.py's static_run dataset (write_transforms: shared intrinsics).
    # Zero and negative principal points and distortion terms are a camera's, not an error;
    # missing ones have defaults (the image centre, no distortion), and so have the object sphere
    # and the camera model (OPENCV, as nerfstudio's); a dataset without its first frame is one of 11.
    legal = {"zero-cx", "negative-cx", "zero-k1", "negative-k1", "missing-k1", "missing-cx",
             "missing-object", "missing-camera_model", "missing-frames.0", "extra-key"}
    return json_cases(numbers=[("fl_x",), ("w",), ("cx",), ("k1",), ("object", "radius")],
                      arrays=[(("object", "center"), 3), (("frames", 0, "transform_matrix"), 4)],
                      others=[("frames",), ("frames", 0), ("frames", 0, "file_path"), ("camera_model",)],
                      skip=lambda cid: cid in legal)


TRANSFORMS = _transforms_doc_cases() + byte_cases(SEED, truncate_at=(0.0, 0.3, 0.9), flips=((2, "head"), (8, "any")))


@pytest.mark.parametrize("case", TRANSFORMS, ids=lambda c: c.id)
def test_transforms_json(capfd, tmp_path, static_run, case: Case):
    folder, _ = static_run
    ds = copy_tree(folder / "ds", odd_dir(tmp_path) / "ds")
    case.apply(ds / "transforms.json")
    out = out_path(tmp_path, "run")
    res = invoke(capfd, "dbb-train", "plenoctree", ds, "-o", out, "--steps", "1", "--res-max", "16")
    check(res, out, may_pass=case.id.startswith("flip-"))


def _crops_doc_cases() -> list[Case]:
    # A frame's time may be 0 (the first) and its split absent (train).
    legal = {"zero-frames.0.time", "missing-frames.0.split", "extra-key"}
    return json_cases(numbers=[("sequence_length",), ("frames", 0, "fl_x"), ("frames", 0, "time")],
                      arrays=[(("up",), 3), (("frames", 0, "transform_matrix"), 4)],
                      others=[("sequences",), ("frames", 0, "split"), ("dbb_dataset_version",)],
                      skip=lambda cid: cid in legal)


CROPS = _crops_doc_cases() + byte_cases(SEED + 1, truncate_at=(0.0, 0.5), flips=((2, "head"),))


@pytest.mark.parametrize("case", CROPS, ids=lambda c: c.id)
def test_crops_json(capfd, tmp_path, dynamic_run, case: Case):
    ds = copy_tree(dynamic_run / "ds", odd_dir(tmp_path) / "ds")
    case.apply(ds / "crops.json")
    out = out_path(tmp_path, "run")
    res = invoke(capfd, "dbb-train", "rssm", ds, "-o", out, "--steps", "1", *SMALL_RSSM)
    check(res, out, may_pass=case.id.startswith("flip-"))


CAMERAS = json_cases(
    numbers=[("fl_x",), ("w",), ("h",), ("frames", 0, "time")],
    arrays=[(("frames", 0, "transform_matrix"), 4)],
    others=[("frames",), ("frames", 0), ("frames", 0, "file_path")],
    # a frame's time is optional and read only by dynamic bundles; a camera's own file_path may be any
    # text; without its first camera the file still holds one
    skip=lambda cid: cid in ("missing-frames.0.time", "null-frames.0.time", "zero-frames.0.time",
                             "negative-frames.0.time", "number-frames.0.file_path", "missing-frames.0"),
    may_pass=lambda cid: cid == "extra-key",
) + byte_cases(SEED + 100, truncate_at=(0.0, 0.3, 0.9), flips=((2, "head"), (8, "any")),
               may_pass=lambda cid: cid.startswith("flip-"))


@pytest.mark.parametrize("case", CAMERAS, ids=lambda c: c.id)
def test_cameras_json(capfd, tmp_path, static_bundle, case: Case):
    cams = odd_dir(tmp_path) / "cameras.json"
    doc = cameras_doc(static_bundle)
    doc["frames"][0]["time"] = 0.0
    cams.write_text(json.dumps(doc))
    case.apply(cams)
    out = out_path(tmp_path, "renders")
    check(invoke(capfd, "dbb-export", "render", static_bundle, "--cameras", cams, "-o", out), out, case.may_pass)


