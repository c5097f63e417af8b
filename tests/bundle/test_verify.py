"""Verifying bundles: a flipped byte anywhere is caught."""

from __future__ import annotations

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
