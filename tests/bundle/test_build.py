"""Building bundles: layout, manifest, model and proxy; zipped bundles; dynamic bundles."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from conftest import gltf_reports

from dbb_capture.bundle.manifest import open_bundle
from dbb_capture.bundle.previews import PREVIEW_PX
from dbb_capture.bundle.render import DynamicRenderer, read_cameras, render_bundle
from dbb_capture.core.errors import DbbError

from .conftest import run_cli


def test_static_bundle_layout_manifest_and_model(static_run, static_bundle):
    folder, _ = static_run
    m = json.loads((static_bundle / "manifest.json").read_text())
    assert m["format"] == "deep-billboard" and m["kind"] == "static" and m["version"] == 1
    (report,) = gltf_reports(static_bundle / "proxy.glb")
    assert (report["errors"], report["warnings"], report["infos"], report["hints"]) == (0, 0, 0, 0), report
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
    assert sheet.shape == (3 * PREVIEW_PX, 6 * PREVIEW_PX, 4) and sheet[..., 3].max() > 0


def test_zip_bundle_verifies_and_a_damaged_zip_does_not(static_run, tmp_path):
    folder, _ = static_run
    z = tmp_path / "toy.dbb"
    assert run_cli("bundle", folder / "run", "-o", z, "--zip").exit_code == 0
    assert run_cli("verify", z).exit_code == 0
    data = bytearray(z.read_bytes())
    data[len(data) // 3] ^= 0xFF
    (tmp_path / "bad.dbb").write_bytes(bytes(data))
    res = run_cli("verify", tmp_path / "bad.dbb")
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign/manifest.json").write_text('{"format": "something-else"}')
    res = run_cli("verify", tmp_path / "foreign")
    assert res.exit_code == 2 and "not a deep-billboard manifest" in res.output
    (tmp_path / "foreign/manifest.json").write_text('{"format": "deep-billboard", "version": 1, "kind": "static"}')
    res = run_cli("render", tmp_path / "foreign", "--cameras", tmp_path / "x.json", "-o", tmp_path / "r")
    assert res.exit_code == 2 and "missing" in res.output and len(res.output.strip().splitlines()) == 1


def test_dynamic_bundle_verifies_renders_in_order_and_has_a_proxy(dynamic_run, tmp_path):
    import trimesh

    from dbb_capture.bundle.proxy import read_glb

    folder = dynamic_run
    res = run_cli("bundle", folder / "run", "-o", folder / "bundle")
    assert res.exit_code == 0, res.output
    b = folder / "bundle"
    m = json.loads((b / "manifest.json").read_text())
    assert m["kind"] == "dynamic" and m["model"]["file"] == "model/stepper.ts"
    assert m["inputs"]["frame_size"] == 32 and len(m["inputs"]["first_view"]) == 3
    assert m["proxy_mesh"]["method"] in ("visual hull", "sphere") and m["proxy_mesh"]["watertight"]
    (report,) = gltf_reports(b / "proxy.glb")
    assert (report["errors"], report["warnings"], report["infos"], report["hints"]) == (0, 0, 0, 0), report
    assert m["proxy_mesh"]["method"] == "visual hull", m["proxy_mesh"]["note"]
    col = read_glb(b / "proxy.glb")["proxy-colonly"]
    assert isinstance(col, trimesh.Trimesh) and col.is_watertight
    assert np.linalg.norm(col.bounds, axis=1).max() <= m["object"]["radius"] * 1.8   # centred, object-sized
    assert (b / "previews/rollout.png").is_file()
    res = run_cli("verify", b)
    assert res.exit_code == 0, res.output
    # Render at the dataset's own crop cameras: one PNG per frame, named after file_path.
    doc = json.loads((folder / "ds/crops.json").read_text())
    doc["frames"] = doc["frames"][:5]
    (tmp_path / "cams.json").write_text(json.dumps(doc))
    res = run_cli("render", b, "--cameras", tmp_path / "cams.json", "-o", tmp_path / "out")
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == [f"{i:05d}.png" for i in range(5)]
    img = cv2.imread(str(tmp_path / "out/00000.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (32, 32, 4)
    # Rendering at a crop camera puts the model's frame in place (the warp is the identity).
    with open_bundle(b) as ob:
        r = DynamicRenderer(ob)
        views = read_cameras(tmp_path / "cams.json")
        crops = r.frames(np.stack([r.view_of(v) for v in views]))
    want = cv2.cvtColor(crops[0], cv2.COLOR_RGBA2BGRA)
    assert np.abs(img.astype(int) - want).max() <= 3
    # --first-frame: any RGBA image; a static bundle refuses it.
    res = run_cli("render", b, "--cameras", tmp_path / "cams.json", "-o", tmp_path / "out2",
               "--first-frame", folder / "ds/crops/00003.png")
    assert res.exit_code == 0, res.output
    with pytest.raises(DbbError):
        render_bundle(b, tmp_path / "cams.json", tmp_path / "out3", first_frame=tmp_path / "nope.png")
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
