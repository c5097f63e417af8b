"""Fuzz: what ``dbb-export bundle``, ``render`` and ``verify`` read, corrupted: a run's tree.npz,
the bundle's PlenOctree .npz and proxy .glb, its manifest.json, and a whole .dbb zip. Files inside a
bundle are also tried "resealed" (the manifest's hashes written again for the damaged file),
so the damage reaches the file's own reader instead of the hash check."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from fuzz.conftest import cameras_doc, check, copy_tree, invoke, odd_dir, out_path, reseal
from fuzz.mutate import Case, byte_cases, json_cases

SEED = 4400


# ------------------------------------------------------------------------------ tree.npz
def _npz_case(cid: str, change) -> Case:
    def apply(path: Path) -> None:
        import numpy as np

        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        change(arrays)
        np.savez_compressed(path, **arrays)
    return Case(cid, apply)


def tree_semantic() -> list[Case]:
    import numpy as np

    def setk(k, fn):
        return lambda a: a.__setitem__(k, fn(a[k]))

    return [
        _npz_case("missing-child", lambda a: a.pop("child")),
        _npz_case("missing-data", lambda a: a.pop("data")),
        _npz_case("child-out-of-range", setk("child", lambda c: c + 10 ** 6)),
        _npz_case("child-negative", setk("child", lambda c: c - 10 ** 6)),
        _npz_case("child-wrong-shape", setk("child", lambda c: c.reshape(c.shape[0], -1))),
        _npz_case("data-wrong-width", setk("data", lambda d: d[..., :-1])),
        _npz_case("data-nan", setk("data", lambda d: np.full_like(d, np.nan))),
        _npz_case("data-fewer-nodes", setk("data", lambda d: d[:1])),
        _npz_case("n-internal-huge", setk("n_internal", lambda n: np.int64(10 ** 12))),
        _npz_case("depth-limit-negative", setk("depth_limit", lambda n: np.int64(-3))),
        _npz_case("invradius-zero", setk("invradius3", lambda v: np.zeros_like(v))),
        _npz_case("offset-nan", setk("offset", lambda v: np.full_like(v, np.nan))),
        _npz_case("data-format-rgba", setk("data_format", lambda v: np.array("RGBA"))),
        _npz_case("data-format-sh5", setk("data_format", lambda v: np.array("SH5"))),
        _npz_case("data-string", setk("data", lambda d: np.array(["x"] * 8))),
    ]


TREE_BYTES = byte_cases(SEED + 5, truncate_at=(0.0, 0.1, 0.5, 0.9, 0.99), flips=((1, "head"), (8, "middle"), (4, "tail")))


@pytest.mark.parametrize("case", TREE_BYTES + tree_semantic(), ids=lambda c: c.id)
def test_tree_npz_bundle(capfd, tmp_path, static_run, case: Case):
    folder, _ = static_run
    run = copy_tree(folder / "run", odd_dir(tmp_path) / "run", ("run.json", "tree.npz", "density_grid.npz"))
    case.apply(run / "tree.npz")
    out = out_path(tmp_path, "bundle")
    res = invoke(capfd, "dbb-export", "bundle", run, "-o", out, "--dataset", folder / "ds")
    check(res, out)


def _bundle_copy(tmp_path, bundle):
    return copy_tree(bundle, odd_dir(tmp_path) / "bundle")


NPZ = byte_cases(SEED + 1, truncate_at=(0.0, 0.1, 0.5, 0.9, 0.99), flips=((1, "head"), (8, "middle"), (4, "tail"))) \
    + tree_semantic()


@pytest.mark.parametrize("case", NPZ, ids=lambda c: c.id)
def test_tree_npz_render(capfd, tmp_path, static_bundle, case: Case):
    b = _bundle_copy(tmp_path, static_bundle)
    cams = tmp_path / "cameras.json"
    cams.write_text(json.dumps(cameras_doc(b)))
    case.apply(b / "model" / "plenoctree.npz")
    out = out_path(tmp_path, "renders")
    check(invoke(capfd, "dbb-export", "render", b, "--cameras", cams, "-o", out), out)


GLB = byte_cases(SEED + 2, truncate_at=(0.0, 0.05, 0.3, 0.7, 0.99),
                 flips=((1, "head"), (4, "head"), (8, "middle"), (4, "tail")),
                 # a flipped byte inside the vertex data is a moved vertex: the mesh still reads
                 may_pass=lambda cid: cid.startswith(("flip-8-middle", "flip-4-tail")))


@pytest.mark.parametrize("sealed", [False, True], ids=["hashed", "resealed"])
@pytest.mark.parametrize("case", GLB, ids=lambda c: c.id)
def test_proxy_glb(capfd, tmp_path, static_bundle, case: Case, sealed: bool):
    b = _bundle_copy(tmp_path, static_bundle)
    case.apply(b / "proxy.glb")
    if sealed:
        reseal(b)
    res = invoke(capfd, "dbb-export", "verify", b)
    check(res, None, may_pass=sealed and case.may_pass)


MANIFEST = json_cases(
    numbers=[("version",), ("object", "radius"), ("previews", "cell_px")],
    arrays=[(("object", "center"), 3), (("up",), 3), (("bundle_from_board",), 4)],
    others=[("format",), ("kind",), ("model",), ("model", "file"), ("files",), ("proxy_mesh",), ("inputs",),
            ("previews", "sheet")],
    # an older version (1) and 0 are read as before; an extra entry is a newer tool's note
    skip=lambda cid: cid in ("zero-version",),
    may_pass=lambda cid: cid == "extra-key",
) + byte_cases(SEED + 3, truncate_at=(0.0, 0.5, 0.95), flips=((2, "head"), (8, "any")))


@pytest.mark.parametrize("command", ["render", "verify"])
@pytest.mark.parametrize("case", MANIFEST, ids=lambda c: c.id)
def test_manifest_json(capfd, tmp_path, static_bundle, case: Case, command: str):
    b = _bundle_copy(tmp_path, static_bundle)
    cams = tmp_path / "cameras.json"
    cams.write_text(json.dumps(cameras_doc(b)))
    case.apply(b / "manifest.json")
    reseal(b)       # the checksum matches: the manifest's own checks must catch the damage
    if command == "render":
        out = out_path(tmp_path, "renders")
        check(invoke(capfd, "dbb-export", "render", b, "--cameras", cams, "-o", out), out, case.may_pass)
    else:
        check(invoke(capfd, "dbb-export", "verify", b), None, case.may_pass)


ZIP = byte_cases(SEED + 4, truncate_at=(0.0, 0.02, 0.3, 0.6, 0.9, 0.99),
                 flips=((1, "head"), (4, "head"), (1, "middle"), (16, "middle"), (4, "tail"), (64, "any")))


@pytest.mark.parametrize("command", ["render", "verify"])
@pytest.mark.parametrize("case", ZIP, ids=lambda c: c.id)
def test_dbb_zip(capfd, tmp_path, static_bundle, static_bundle_zip, case: Case, command: str):
    z = odd_dir(tmp_path) / "static.dbb"
    shutil.copy2(static_bundle_zip, z)
    case.apply(z)
    if command == "render":
        cams = tmp_path / "cameras.json"
        cams.write_text(json.dumps(cameras_doc(static_bundle)))
        out = out_path(tmp_path, "renders")
        check(invoke(capfd, "dbb-export", "render", z, "--cameras", cams, "-o", out), out)
    else:
        check(invoke(capfd, "dbb-export", "verify", z), None)
