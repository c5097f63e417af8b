"""Rendering bundles: equal to the run's tree, both intrinsics layouts, bundle space, bad input."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np

from dbb_capture.core.images import to_u8

from .conftest import run_cli, write_cameras


def test_render_equals_the_runs_tree_and_reads_both_intrinsic_layouts(static_run, static_bundle, tmp_path):
    from dbb_capture.octree.render import TreeRenderer
    from dbb_capture.octree.tree import PlenOctree

    folder, frames = static_run
    test = frames[:3]
    ref = TreeRenderer(PlenOctree.load(folder / "run/tree.npz"))
    for per_frame in (False, True):
        cams = write_cameras(test, tmp_path / f"cams{per_frame}.json", per_frame)
        out = tmp_path / f"out{per_frame}"
        out.mkdir()                                       # an empty folder made for the output is fine
        res = run_cli("render", static_bundle, "--cameras", cams, "-o", out)
        assert res.exit_code == 0, res.output
        assert sorted(p.name for p in out.iterdir()) == sorted(f"{f.name}.png" for f in test)
        for f in test:
            got = cv2.cvtColor(cv2.imread(str(out / f"{f.name}.png"), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)
            want = to_u8(ref.render(f.c2w, f.intr))
            assert got.shape == (24, 24, 4)
            assert np.abs(got.astype(int) - want).max() <= 1


def test_render_in_bundle_space_matches_board_space(static_bundle, static_run, tmp_path):
    from dbb_capture.geometry.conventions import opencv_from_opengl, opengl_from_opencv

    _, frames = static_run
    T = np.asarray(json.loads((static_bundle / "manifest.json").read_text())["bundle_from_board"])
    cams = write_cameras(frames[:2], tmp_path / "board.json")
    doc = json.loads(cams.read_text())
    for d in doc["frames"]:
        d["transform_matrix"] = opengl_from_opencv(T @ opencv_from_opengl(np.asarray(d["transform_matrix"]))).tolist()
    (tmp_path / "bundle.json").write_text(json.dumps(doc))
    assert run_cli("render", static_bundle, "--cameras", cams, "-o", tmp_path / "a").exit_code == 0
    assert run_cli("render", static_bundle, "--cameras", tmp_path / "bundle.json", "-o", tmp_path / "b",
                "--space", "bundle").exit_code == 0
    for p in (tmp_path / "a").iterdir():
        a, b = cv2.imread(str(p), cv2.IMREAD_UNCHANGED), cv2.imread(str(tmp_path / "b" / p.name), cv2.IMREAD_UNCHANGED)
        assert np.abs(a.astype(int) - b).max() <= 2


def test_bad_input_is_one_line_exit_2_and_leaves_nothing(static_run, static_bundle, tmp_path):
    folder, frames = static_run
    # A run folder that is not a finished training run.
    (tmp_path / "half").mkdir()
    res = run_cli("bundle", tmp_path / "half", "-o", tmp_path / "b1")
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1
    shutil.copytree(folder / "run", tmp_path / "broken")
    (tmp_path / "broken/tree.npz").unlink()
    res = run_cli("bundle", tmp_path / "broken", "-o", tmp_path / "b2")
    assert res.exit_code == 2 and "tree.npz is missing" in res.output
    assert not (tmp_path / "b2").exists() and not list(tmp_path.glob(".b2*"))
    meta = json.loads((folder / "run/run.json").read_text())
    (tmp_path / "broken/run.json").write_text(json.dumps({k: v for k, v in meta.items() if k != "tree"}))
    res = run_cli("bundle", tmp_path / "broken", "-o", tmp_path / "b2")
    assert res.exit_code == 2 and "lacks tree.file" in res.output
    # The run's dataset moved: say so and how to point at it.
    shutil.copytree(folder / "run", tmp_path / "moved")
    (tmp_path / "moved/run.json").write_text(json.dumps(meta | {"dataset": str(tmp_path / "gone")}))
    res = run_cli("bundle", tmp_path / "moved", "-o", tmp_path / "b3")
    assert res.exit_code == 2 and "--dataset" in res.output and not (tmp_path / "b3").exists()
    assert run_cli("bundle", tmp_path / "moved", "-o", tmp_path / "b3", "--dataset", folder / "ds").exit_code == 0
    # Existing output without --overwrite.
    assert run_cli("bundle", folder / "run", "-o", static_bundle).exit_code == 2
    # Cameras without intrinsics.
    cams = write_cameras(frames[:2], tmp_path / "noint.json", drop_intrinsics=True)
    res = run_cli("render", static_bundle, "--cameras", cams, "-o", tmp_path / "r")
    assert res.exit_code == 2 and "intrinsics" in res.output and len(res.output.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists()
    # Not a bundle at all.
    res = run_cli("render", tmp_path / "half", "--cameras", cams, "-o", tmp_path / "r")
    assert res.exit_code == 2 and "not a deep-billboard bundle" in res.output
