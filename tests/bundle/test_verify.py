"""Verifying bundles: a flipped byte anywhere is caught."""

from __future__ import annotations

import json
import shutil

from .conftest import run_cli


def test_verify_passes_then_catches_a_flipped_byte_anywhere(static_bundle, tmp_path):
    res = run_cli("verify", static_bundle)
    assert res.exit_code == 0, res.output
    for rel in ("manifest.json", "model/plenoctree.npz", "proxy.glb", "previews/sheet.png"):
        bad = tmp_path / rel.replace("/", "_")
        shutil.copytree(static_bundle, bad)
        p = bad / rel
        data = bytearray(p.read_bytes())
        data[len(data) // 2] ^= 0x01
        p.write_bytes(bytes(data))
        res = run_cli("verify", bad)
        assert res.exit_code == 2, (rel, res.output)
        assert len(res.output.strip().splitlines()) == 1 and "error" in res.output
    shutil.copytree(static_bundle, tmp_path / "stray")
    (tmp_path / "stray/extra.bin").write_bytes(b"x")
    res = run_cli("verify", tmp_path / "stray")
    assert res.exit_code == 2 and "not in the manifest: extra.bin" in res.output


def _edit_manifest(src, dst, edit):
    """A copy of the bundle ``src`` at ``dst`` with its manifest changed by ``edit`` (checksum redone)."""
    from dbb_capture.bundle.manifest import CHECKSUM, MANIFEST, sha256_of

    shutil.copytree(src, dst)
    m = json.loads((dst / MANIFEST).read_text())
    edit(m)
    (dst / MANIFEST).write_text(json.dumps(m))
    (dst / CHECKSUM).write_text(f"{sha256_of(dst / MANIFEST)}  {MANIFEST}\n")
    return dst


def test_the_support_plane_is_checked_and_bundles_without_one_still_verify(dynamic_bundle, tmp_path):
    from dbb_capture.bundle.proxy import read_glb

    m = json.loads((dynamic_bundle / "manifest.json").read_text())
    plane = m["support_plane"]                   # a dbb-capture dataset: the board plane, bundle space
    assert plane["normal"] == [0.0, 1.0, 0.0] and plane["point"][1] < 0
    col = read_glb(dynamic_bundle / "proxy.glb")["proxy-colonly"]
    assert abs(col.bounds[0][1] - plane["point"][1]) < 1e-3 and m["proxy_mesh"]["base_above_support_m"] == 0.0
    res = run_cli("verify", dynamic_bundle)
    assert res.exit_code == 0 and "lowest point 0.0 mm above the support plane" in res.output, res.output
    # A bundle from before the support plane (no entry) verifies as it did.
    old = _edit_manifest(dynamic_bundle, tmp_path / "old", lambda d: d.pop("support_plane"))
    res = run_cli("verify", old)
    assert res.exit_code == 0 and "support plane" not in res.output, res.output
    # A proxy that reaches under its plane, or a plane that is not one: one line, exit 2.
    high = _edit_manifest(dynamic_bundle, tmp_path / "high",
                          lambda d: d["support_plane"].update(point=[0.0, plane["point"][1] + 0.05, 0.0]))
    res = run_cli("verify", high)
    assert res.exit_code == 2 and "reaches 50.0 mm under its support plane" in res.output, res.output
    bad = _edit_manifest(dynamic_bundle, tmp_path / "bad", lambda d: d["support_plane"].update(normal=[0, 2, "x"]))
    res = run_cli("verify", bad)
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1 and "support_plane" in res.output
