"""Verifying a bundle: checksum, schema, every file's hash, the proxy's nodes, and a fresh render
against the stored preview."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.errors import DbbError
from .manifest import CHECKSUM, MANIFEST, open_bundle, sha256_of
from .previews import cell, orbit_view, tile
from .proxy import read_glb
from .render import DynamicRenderer, StaticRenderer, read_rgba

CHECK_PSNR_DB = 35.0        # verify: a fresh render must match the stored preview this closely
SUPPORT_TOLERANCE_M = 1e-3  # verify: the proxy may reach this far under its support plane (float32 glTF)


def verify_bundle(path: Path) -> list[str]:
    """Check a bundle: manifest checksum and schema, every file's size and sha256, no stray
    files, the model loads, the proxy mesh reads with its collision nodes, and a fresh render
    matches the stored preview. Returns what passed; raises :class:`DbbError` at the first failure."""
    from ..core.metrics import psnr_from_mse

    done = []
    with open_bundle(path) as b:
        m = b.manifest
        ck = (b.root / CHECKSUM)
        if not ck.is_file():
            raise DbbError(f"{path}: {CHECKSUM} is missing")
        want = ck.read_text().split()[0] if ck.read_text().split() else ""
        if sha256_of(b.root / MANIFEST) != want:
            raise DbbError(f"{path}: {MANIFEST} does not match {CHECKSUM} (the manifest was changed or damaged)")
        done.append(f"manifest: format {m.format} v{m.version}, kind {m.kind}, checksum ok")
        listed = {e.path for e in m.files}
        for e in m.files:
            p = b.file(e.path)
            if p.stat().st_size != e.bytes:
                raise DbbError(f"{path}: {e.path} is {p.stat().st_size} bytes, manifest says {e.bytes}")
            if sha256_of(p) != e.sha256:
                raise DbbError(f"{path}: {e.path} fails its sha256 check (changed or damaged)")
        present = {p.relative_to(b.root).as_posix() for p in b.root.rglob("*") if p.is_file()}
        stray = sorted(present - listed - {MANIFEST, CHECKSUM})
        if stray:
            raise DbbError(f"{path}: files not in the manifest: {', '.join(stray[:3])}")
        done.append(f"files: {len(m.files)} match their sha256 and size")
        meshes = read_glb(b.file(m.proxy_mesh["file"]))
        names = sorted(meshes)
        if not any(n.endswith("-colonly") for n in names) or not any(n.endswith("-convcolonly") for n in names):
            raise DbbError(f"{path}: proxy mesh lacks its -colonly / -convcolonly nodes (has {names})")
        line = f"proxy mesh: nodes {', '.join(names)}"
        if m.support is not None:             # bundles from before the support plane have none
            point, normal = m.support
            low = min(float(((np.asarray(t.vertices) - point) @ normal).min()) for t in meshes.values())
            if low < -SUPPORT_TOLERANCE_M:
                raise DbbError(f"{path}: the proxy mesh reaches {-low * 1000:.1f} mm under its support plane "
                               f"(the table; allowed {SUPPORT_TOLERANCE_M * 1000:.0f} mm)")
            line += (f"; lowest point {max(low, 0.0) * 1000:.1f} mm above the support plane" if low > -5e-5 else
                     f"; lowest point {-low * 1000:.1f} mm under the support plane")
        done.append(line)
        pv = m.previews
        sheet = read_rgba(b.file(pv["sheet"]["file"]))
        cols, S = int(pv["sheet"]["columns"]), int(pv["cell_px"])
        if m.kind == "static":
            r = StaticRenderer(b.file(m.model["file"]))
            a, e, d = pv["sheet"]["views"][0]
            fresh = r.render([orbit_view("check", m.T, m.radius, a, e, d)])[0]
            stored = cell(sheet, 0, cols, S)
            what = "sheet view 0"
        else:
            r = DynamicRenderer(b)
            rows = pv["rollout"]["rows"]
            fresh = tile(list(r.frames(np.array(rows["still"]), seed=int(pv["rollout"]["seed"]))), 16)
            stored = read_rgba(b.file(pv["rollout"]["file"]))[:S]
            what = "rollout row 1"
        done.append(f"model: {m.model['file']} loads")
        if fresh.shape != stored.shape:
            raise DbbError(f"{path}: a fresh render of {what} is {fresh.shape}, the stored preview {stored.shape}")
        p = psnr_from_mse(float((((fresh.astype(np.float32) - stored.astype(np.float32)) / 255.0) ** 2).mean()))
        if p < CHECK_PSNR_DB:
            raise DbbError(f"{path}: a fresh render of {what} differs from the stored preview ({p:.1f} dB < "
                           f"{CHECK_PSNR_DB:.0f} dB)")
        done.append(f"render: {what} matches the stored preview ({p:.1f} dB)")
    return done
