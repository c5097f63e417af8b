"""Bundles: build from static and dynamic runs, zip, verify (catches a flipped byte), render, bad input."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from dbb_capture.cli.export import main

from dbb_capture.bundle import build as B
from dbb_capture.core.errors import DbbError

torch.set_num_threads(1)


def _cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def static_run(tmp_path_factory):
    """A tiny PlenOctree run (a few steps on 24 px views of the synthetic toy)."""
    from static.synthetic import synthetic_object_frames

    from dbb_capture.datasets.transforms import write_transforms
    from dbb_capture.static.field import FieldConfig
    from dbb_capture.static.run import RunConfig, train_run

    folder = tmp_path_factory.mktemp("bundle_static")
    (folder / "ds").mkdir()
    frames, vol = synthetic_object_frames(folder / "ds", n=12, size=24, seed=2)
    write_transforms(folder / "ds" / "transforms.json", frames, vol)
    torch.manual_seed(0)
    cfg = FieldConfig(res_start=16, res_max=32, batch_rays=512, upsample_at=(0.3,), tv_points=2048)
    train_run(folder / "ds", folder / "run", RunConfig(steps=20), cfg, quiet=True)
    return folder, frames


@pytest.fixture(scope="module")
def static_bundle(static_run):
    folder, _ = static_run
    res = _cli("bundle", folder / "run", "-o", folder / "bundle")
    assert res.exit_code == 0, res.output
    return folder / "bundle"


@pytest.fixture(scope="module")
def dynamic_run(tmp_path_factory):
    from dbb_capture.dynamic.config import RssmConfig, TrainConfig
    from dbb_capture.dynamic.run import train_run
    from dbb_capture.synth.crops import synthetic_crops

    folder = tmp_path_factory.mktemp("bundle_dynamic")
    synthetic_crops(folder / "ds", seconds=3.0, fps=10, size=32, still_steps=1, samples=1)
    small = RssmConfig(size=32, deter=16, stoch=16, hidden=64, embed=64, enc_depth=8, dec_depth=8)
    train_run(folder / "ds", folder / "run", small, TrainConfig(steps=3, batch=2), quiet=True)
    return folder


def test_static_bundle_layout_manifest_and_model(static_run, static_bundle):
    folder, _ = static_run
    m = json.loads((static_bundle / "manifest.json").read_text())
    assert m["format"] == "deep-billboard" and m["kind"] == "static" and m["version"] == 1
    assert (static_bundle / "model/plenoctree.npz").read_bytes() == (folder / "run/tree.npz").read_bytes()
    z = np.load(static_bundle / "model/plenoctree.npz")     # the keys svox's N3Tree.load reads
    assert {"data", "child", "parent_depth", "n_internal", "n_free", "invradius3", "offset", "depth_limit",
            "geom_resize_fact", "data_dim", "data_format"} <= set(z.files)
    assert m["up"] == [0.0, 0.0, -1.0]                       # derived from the cameras (above the board)
    T = np.asarray(m["bundle_from_board"])
    assert np.allclose(T[:3, :3] @ m["object"]["center"] + T[:3, 3], 0)
    assert np.allclose(T[1, :3], m["up"])
    files = {e["path"]: e for e in m["files"]}
    assert set(files) == {"model/plenoctree.npz", "proxy.glb", "previews/turntable.gif", "previews/sheet.png"}
    assert files["proxy.glb"]["bytes"] == (static_bundle / "proxy.glb").stat().st_size
    pm = m["proxy_mesh"]
    assert pm["watertight"] and pm["triangles"] <= 5000 and pm["method"] == "marching cubes"
    sheet = cv2.imread(str(static_bundle / "previews/sheet.png"), cv2.IMREAD_UNCHANGED)
    assert sheet.shape == (3 * B.PREVIEW_PX, 6 * B.PREVIEW_PX, 4) and sheet[..., 3].max() > 0


def test_verify_passes_then_catches_a_flipped_byte_anywhere(static_bundle, tmp_path):
    res = _cli("verify", static_bundle)
    assert res.exit_code == 0, res.output
    for rel in ("manifest.json", "model/plenoctree.npz", "proxy.glb", "previews/sheet.png"):
        bad = tmp_path / rel.replace("/", "_")
        shutil.copytree(static_bundle, bad)
        p = bad / rel
        data = bytearray(p.read_bytes())
        data[len(data) // 2] ^= 0x01
        p.write_bytes(bytes(data))
        res = _cli("verify", bad)
        assert res.exit_code == 2, (rel, res.output)
        assert len(res.output.strip().splitlines()) == 1 and "error" in res.output
    shutil.copytree(static_bundle, tmp_path / "stray")
    (tmp_path / "stray/extra.bin").write_bytes(b"x")
    res = _cli("verify", tmp_path / "stray")
    assert res.exit_code == 2 and "not in the manifest: extra.bin" in res.output


def test_zip_bundle_verifies_and_a_damaged_zip_does_not(static_run, tmp_path):
    folder, _ = static_run
    z = tmp_path / "toy.dbb"
    assert _cli("bundle", folder / "run", "-o", z, "--zip").exit_code == 0
    assert _cli("verify", z).exit_code == 0
    data = bytearray(z.read_bytes())
    data[len(data) // 3] ^= 0xFF
    (tmp_path / "bad.dbb").write_bytes(bytes(data))
    res = _cli("verify", tmp_path / "bad.dbb")
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign/manifest.json").write_text('{"format": "something-else"}')
    res = _cli("verify", tmp_path / "foreign")
    assert res.exit_code == 2 and "not a deep-billboard manifest" in res.output
    (tmp_path / "foreign/manifest.json").write_text('{"format": "deep-billboard", "version": 1, "kind": "static"}')
    res = _cli("render", tmp_path / "foreign", "--cameras", tmp_path / "x.json", "-o", tmp_path / "r")
    assert res.exit_code == 2 and "missing" in res.output and len(res.output.strip().splitlines()) == 1


def _cameras(frames, path, per_frame=False, drop_intrinsics=False):
    from dbb_capture.geometry.conventions import opengl_from_opencv

    doc = {"frames": [{"file_path": f"images/{f.name}.jpg",
                       "transform_matrix": opengl_from_opencv(f.c2w).tolist()} for f in frames]}
    intr = frames[0].intr.nerfstudio_fields()
    if not drop_intrinsics:
        if per_frame:
            for d in doc["frames"]:
                d.update(intr)
        else:
            doc.update(intr)
    path.write_text(json.dumps(doc))
    return path


def test_render_equals_the_runs_tree_and_reads_both_intrinsic_layouts(static_run, static_bundle, tmp_path):
    from dbb_capture.octree.render import TreeRenderer
    from dbb_capture.octree.tree import PlenOctree

    folder, frames = static_run
    test = frames[:3]
    ref = TreeRenderer(PlenOctree.load(folder / "run/tree.npz"))
    for per_frame in (False, True):
        cams = _cameras(test, tmp_path / f"cams{per_frame}.json", per_frame)
        out = tmp_path / f"out{per_frame}"
        out.mkdir()                                       # an empty folder made for the output is fine
        res = _cli("render", static_bundle, "--cameras", cams, "-o", out)
        assert res.exit_code == 0, res.output
        assert sorted(p.name for p in out.iterdir()) == sorted(f"{f.name}.png" for f in test)
        for f in test:
            got = cv2.cvtColor(cv2.imread(str(out / f"{f.name}.png"), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)
            want = B.to_u8(ref.render(f.c2w, f.intr))
            assert got.shape == (24, 24, 4)
            assert np.abs(got.astype(int) - want).max() <= 1


def test_render_in_bundle_space_matches_board_space(static_bundle, static_run, tmp_path):
    from dbb_capture.geometry.conventions import opencv_from_opengl, opengl_from_opencv

    _, frames = static_run
    T = np.asarray(json.loads((static_bundle / "manifest.json").read_text())["bundle_from_board"])
    cams = _cameras(frames[:2], tmp_path / "board.json")
    doc = json.loads(cams.read_text())
    for d in doc["frames"]:
        d["transform_matrix"] = opengl_from_opencv(T @ opencv_from_opengl(np.asarray(d["transform_matrix"]))).tolist()
    (tmp_path / "bundle.json").write_text(json.dumps(doc))
    assert _cli("render", static_bundle, "--cameras", cams, "-o", tmp_path / "a").exit_code == 0
    assert _cli("render", static_bundle, "--cameras", tmp_path / "bundle.json", "-o", tmp_path / "b",
                "--space", "bundle").exit_code == 0
    for p in (tmp_path / "a").iterdir():
        a, b = cv2.imread(str(p), cv2.IMREAD_UNCHANGED), cv2.imread(str(tmp_path / "b" / p.name), cv2.IMREAD_UNCHANGED)
        assert np.abs(a.astype(int) - b).max() <= 2


def test_bad_input_is_one_line_exit_2_and_leaves_nothing(static_run, static_bundle, tmp_path):
    folder, frames = static_run
    # A run folder that is not a finished training run.
    (tmp_path / "half").mkdir()
    res = _cli("bundle", tmp_path / "half", "-o", tmp_path / "b1")
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1
    shutil.copytree(folder / "run", tmp_path / "broken")
    (tmp_path / "broken/tree.npz").unlink()
    res = _cli("bundle", tmp_path / "broken", "-o", tmp_path / "b2")
    assert res.exit_code == 2 and "tree.npz is missing" in res.output
    assert not (tmp_path / "b2").exists() and not list(tmp_path.glob(".b2*"))
    meta = json.loads((folder / "run/run.json").read_text())
    (tmp_path / "broken/run.json").write_text(json.dumps({k: v for k, v in meta.items() if k != "tree"}))
    res = _cli("bundle", tmp_path / "broken", "-o", tmp_path / "b2")
    assert res.exit_code == 2 and "lacks tree.file" in res.output
    # The run's dataset moved: say so and how to point at it.
    shutil.copytree(folder / "run", tmp_path / "moved")
    (tmp_path / "moved/run.json").write_text(json.dumps(meta | {"dataset": str(tmp_path / "gone")}))
    res = _cli("bundle", tmp_path / "moved", "-o", tmp_path / "b3")
    assert res.exit_code == 2 and "--dataset" in res.output and not (tmp_path / "b3").exists()
    assert _cli("bundle", tmp_path / "moved", "-o", tmp_path / "b3", "--dataset", folder / "ds").exit_code == 0
    # Existing output without --overwrite.
    assert _cli("bundle", folder / "run", "-o", static_bundle).exit_code == 2
    # Cameras without intrinsics.
    cams = _cameras(frames[:2], tmp_path / "noint.json", drop_intrinsics=True)
    res = _cli("render", static_bundle, "--cameras", cams, "-o", tmp_path / "r")
    assert res.exit_code == 2 and "intrinsics" in res.output and len(res.output.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists()
    # Not a bundle at all.
    res = _cli("render", tmp_path / "half", "--cameras", cams, "-o", tmp_path / "r")
    assert res.exit_code == 2 and "not a deep-billboard bundle" in res.output


def test_dynamic_bundle_verifies_renders_in_order_and_has_a_proxy(dynamic_run, tmp_path):
    import trimesh

    from dbb_capture.bundle.proxy import read_glb

    folder = dynamic_run
    res = _cli("bundle", folder / "run", "-o", folder / "bundle")
    assert res.exit_code == 0, res.output
    b = folder / "bundle"
    m = json.loads((b / "manifest.json").read_text())
    assert m["kind"] == "dynamic" and m["model"]["file"] == "model/stepper.ts"
    assert m["inputs"]["frame_size"] == 32 and len(m["inputs"]["first_view"]) == 3
    assert m["proxy_mesh"]["method"] in ("visual hull", "sphere") and m["proxy_mesh"]["watertight"]
    assert m["proxy_mesh"]["method"] == "visual hull", m["proxy_mesh"]["note"]
    col = read_glb(b / "proxy.glb")["proxy-colonly"]
    assert isinstance(col, trimesh.Trimesh) and col.is_watertight
    assert np.linalg.norm(col.bounds, axis=1).max() <= m["object"]["radius"] * 1.8   # centred, object-sized
    assert (b / "previews/rollout.png").is_file()
    res = _cli("verify", b)
    assert res.exit_code == 0, res.output
    # Render at the dataset's own crop cameras: one PNG per frame, named after file_path.
    doc = json.loads((folder / "ds/crops.json").read_text())
    doc["frames"] = doc["frames"][:5]
    (tmp_path / "cams.json").write_text(json.dumps(doc))
    res = _cli("render", b, "--cameras", tmp_path / "cams.json", "-o", tmp_path / "out")
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == [f"{i:05d}.png" for i in range(5)]
    img = cv2.imread(str(tmp_path / "out/00000.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (32, 32, 4)
    # Rendering at a crop camera puts the model's frame in place (the warp is the identity).
    with B.open_bundle(b) as ob:
        r = B.DynamicRenderer(ob)
        views = B.read_cameras(tmp_path / "cams.json")
        crops = r.frames(np.stack([r.view_of(v) for v in views]))
    want = cv2.cvtColor(crops[0], cv2.COLOR_RGBA2BGRA)
    assert np.abs(img.astype(int) - want).max() <= 3
    # --first-frame: any RGBA image; a static bundle refuses it.
    res = _cli("render", b, "--cameras", tmp_path / "cams.json", "-o", tmp_path / "out2",
               "--first-frame", folder / "ds/crops/00003.png")
    assert res.exit_code == 0, res.output
    with pytest.raises(DbbError):
        B.render_bundle(b, tmp_path / "cams.json", tmp_path / "out3", first_frame=tmp_path / "nope.png")
    assert not (tmp_path / "out3").exists()


def test_dynamic_proxy_falls_back_to_a_sphere_and_says_why(dynamic_run, tmp_path):
    from dbb_capture.bundle.proxy import bundle_from_board, dynamic_proxy

    doc = json.loads((dynamic_run / "ds/crops.json").read_text())
    doc["frames"] = doc["frames"][:2]
    (dynamic_run / "ds/two.json").write_text(json.dumps(doc))
    c, r = np.asarray(doc["object"]["center"]), doc["object"]["radius"]
    p = dynamic_proxy(dynamic_run / "ds/two.json", c, r, bundle_from_board(c, np.asarray(doc["up"])))
    assert p.method == "sphere" and "only 2 views" in p.note and p.watertight
    assert 0.2 * r < np.abs(p.vertices).max() <= r * 1.01


def test_preview_orbit_agrees_with_the_viewpoint_convention():
    from dbb_capture.geometry.viewpoint import viewpoint
    from dbb_capture.bundle.proxy import bundle_from_board

    c = np.array([0.4, 0.1, -0.09])
    for up in (np.array([0, 0, -1.0]), np.array([0, 0, 1.0])):
        T = bundle_from_board(c, up)
        for a, e in ((0.0, 20.0), (75.0, 45.0), (-130.0, 10.0)):
            v = B.orbit_view("x", T, 0.1, a, e, 0.5)
            p = viewpoint(v.c2w[:3, 3], c, up)
            assert (p.azimuth_deg, p.elevation_deg, p.distance_m) == pytest.approx((a, e, 0.5), abs=1e-6)
            assert np.allclose(v.c2w[:3, 2], (c - v.c2w[:3, 3]) / 0.5)     # looks at the centre
