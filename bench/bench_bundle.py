"""Bundle benchmarks: proxy mesh against the true shape, renders from a bundle
against the training run's renders, verify against a flipped byte. Figures go to docs/results.md.

    python bench/bench_bundle.py static RUN OUT [--capture CAPTURE | --seed 0]
    python bench/bench_bundle.py dynamic RUN OUT [--seed 0]

``static``: RUN is a ``dbb-train plenoctree`` run of a synthetic static object; the true shape is
the object model of ``--capture`` (``dbb-capture synth`` ground truth) or, by default, the object
``bench_plenoctree.py synth`` renders (``make_object("static", 7x5 board, seed)``). Both shapes are
voxelised in the board frame (the mesh is taken there by the inverse of ``bundle_from_board``).
``dynamic``: RUN is a ``dbb-train rssm`` run; renders at the dataset's crop cameras are compared
with the run's own stepper rolled out from the same first frame and seed.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
from common import emit  # bench/ is the script folder: on sys.path

from dbb_capture.bundle.build import make_bundle
from dbb_capture.bundle.manifest import MANIFEST, open_bundle
from dbb_capture.bundle.proxy import read_glb, transform_points
from dbb_capture.bundle.render import (
    SEED,
    DynamicRenderer,
    read_cameras,
    read_rgba,
    render_bundle,
    rgba_tensor,
)
from dbb_capture.bundle.verify import verify_bundle
from dbb_capture.core.errors import DbbError
from dbb_capture.core.images import to_u8
from dbb_capture.core.metrics import psnr_from_mse
from dbb_capture.datasets.transforms import intrinsics_fields
from dbb_capture.geometry.conventions import opengl_from_opencv


def true_occupancy(model, t: float, points: np.ndarray) -> np.ndarray:
    """Inside the synthetic object (union of posed ellipsoids) at time t, for points (N, 3)."""
    inside = np.zeros(len(points), bool)
    for c, R, e in model.posed(t):
        q = (points - c) @ R / np.asarray(e.radii)
        inside |= (q ** 2).sum(1) <= 1
    return inside


def mesh_occupancy(v: np.ndarray, f: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Inside a closed mesh, for points (N, 3) (open3d ray casting)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    occ = scene.compute_occupancy(o3d.core.Tensor(points.astype(np.float32)))
    return occ.numpy().astype(bool)


def flipped_byte_caught(bundle: Path, scratch: Path) -> dict:
    """Flip one byte in the middle of every file of a copy of the bundle: does verify refuse each?"""
    out = {}
    with open_bundle(bundle) as b:
        rels = [MANIFEST] + [e.path for e in b.manifest.files]
    for rel in rels:
        bad = scratch / "flipped"
        shutil.rmtree(bad, ignore_errors=True)
        shutil.copytree(bundle, bad)
        data = bytearray((bad / rel).read_bytes())
        data[len(data) // 2] ^= 0x01
        (bad / rel).write_bytes(bytes(data))
        try:
            verify_bundle(bad)
            out[rel] = "NOT caught"
        except DbbError as e:
            out[rel] = f"caught: {str(e).split(': ', 1)[-1][:80]}"
    shutil.rmtree(scratch / "flipped", ignore_errors=True)
    return out


def bench_static(run: Path, out: Path, capture: Path | None, seed: int, res: int) -> dict:
    from dbb_capture.datasets.images import load_rgba
    from dbb_capture.datasets.transforms import load_dataset
    from dbb_capture.octree.render import TreeRenderer
    from dbb_capture.static.run import load_run

    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    m = make_bundle(run, out / "bundle", overwrite=True)
    bundle_s = time.perf_counter() - t
    if capture is not None:
        from dbb_capture.synth.capture import load_ground_truth

        model = load_ground_truth(capture)[2]
    else:
        from dbb_capture.capture.board import BoardSpec
        from dbb_capture.synth.objects import make_object

        model = make_object("static", BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100"), np.random.default_rng(seed))
    # Voxelise both over the object's cube in the board frame.
    c, r = m.center, m.radius
    ax = (np.arange(res) + 0.5) / res * 2 - 1
    P = c + r * np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    col = read_glb(out / "bundle" / m.proxy_mesh["file"])["proxy-colonly"]
    v_board = transform_points(np.linalg.inv(m.T), np.asarray(col.vertices))
    mine = mesh_occupancy(v_board, np.asarray(col.faces), P)
    truth = true_occupancy(model, 0.0, P)
    iou = float((mine & truth).sum() / max(1, (mine | truth).sum()))
    # Renders from the bundle (dbb-export render, 8-bit PNG) vs the run's own tree renders, both vs truth.
    ds = load_dataset(Path(load_run(run).record.dataset))
    test = ds.split("test") or ds.frames[::8]
    cams = {"frames": [{"file_path": f"{f.name}.png", "transform_matrix": opengl_from_opencv(f.c2w).tolist(),
                        **intrinsics_fields(f.intr)} for f in test]}
    (out / "cameras.json").write_text(json.dumps(cams))
    t = time.perf_counter()
    render_bundle(out / "bundle", out / "cameras.json", out / "renders", overwrite=True)
    render_s = time.perf_counter() - t
    ref = TreeRenderer(load_run(run).tree())
    rows = []
    for f in test:
        gt = load_rgba(f)
        gt_w = gt[..., :3] * gt[..., 3:] + 1 - gt[..., 3:]
        got = read_rgba(out / "renders" / f"{f.name}.png").astype(np.float32) / 255
        got_w = got[..., :3] * got[..., 3:] + 1 - got[..., 3:]
        run_img = ref.render(f.c2w, f.intr, (1.0, 1.0, 1.0))
        rows.append({"bundle": psnr_from_mse(float(((got_w - gt_w) ** 2).mean())),
                     "run": psnr_from_mse(float(((run_img - gt_w) ** 2).mean())),
                     "bundle_vs_run": psnr_from_mse(float(((got_w - run_img) ** 2).mean()))})
    t = time.perf_counter()
    checks = verify_bundle(out / "bundle")
    verify_s = time.perf_counter() - t
    pm = m.proxy_mesh
    return {"run": str(run), "bundle_seconds": round(bundle_s, 1), "proxy": pm,
            "iou_board_frame": round(iou, 4), "iou_grid": f"{res}^3 over the object cube",
            "renders": len(rows), "render_seconds": round(render_s, 2),
            "psnr_white_bundle": round(float(np.mean([x["bundle"] for x in rows])), 3),
            "psnr_white_run": round(float(np.mean([x["run"] for x in rows])), 3),
            "psnr_bundle_vs_run_min": round(float(np.min([x["bundle_vs_run"] for x in rows])), 2),
            "verify_seconds": round(verify_s, 1), "verify": checks,
            "flipped_byte": flipped_byte_caught(out / "bundle", out)}


def hull_iou(m, bundle: Path, times: np.ndarray, seed: int, res: int) -> dict:
    """IoU of the proxy with the synthetic dynamic toy (``synth.crops.synthetic_crops``' object, ``seed``):
    against what it occupies in >= 90 % of the frame times (what the carving keeps), and at t = 0."""
    from dbb_capture.synth.objects import make_object
    from dbb_capture.synth.scene import SynthConfig

    model = make_object("dynamic", SynthConfig().board, np.random.default_rng(seed))
    c, r = m.center, m.radius
    ax = (np.arange(res) + 0.5) / res * 2 - 1
    P = c + r * np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    col = read_glb(bundle / m.proxy_mesh["file"])["proxy-colonly"]
    mine = mesh_occupancy(transform_points(np.linalg.inv(m.T), np.asarray(col.vertices)), np.asarray(col.faces), P)
    ts = times[:: max(1, len(times) // 60)]
    frac = np.mean([true_occupancy(model, float(t), P) for t in ts], axis=0)

    def iou(a, b):
        return round(float((a & b).sum() / max(1, (a | b).sum())), 4)

    return {"iou_vs_occupied_90pct_of_time": iou(mine, frac >= 0.9), "iou_vs_t0": iou(mine, true_occupancy(model, 0.0, P)),
            "times_sampled": len(ts), "grid": f"{res}^3 over the object cube"}


def bench_dynamic(run: Path, out: Path, seed: int | None, res: int) -> dict:
    from dbb_capture.dynamic.stepper import rollout

    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    m = make_bundle(run, out / "bundle", overwrite=True)
    bundle_s = time.perf_counter() - t
    meta = json.loads((run / "run.json").read_text())
    doc = json.loads((Path(meta["dataset"]) / "crops.json").read_text())
    times = np.array([f["time"] for f in doc["frames"]])
    doc["frames"] = doc["frames"][:24]
    (out / "cameras.json").write_text(json.dumps(doc))
    t = time.perf_counter()
    render_bundle(out / "bundle", out / "cameras.json", out / "renders", overwrite=True)
    render_s = time.perf_counter() - t
    # The run's own stepper, same first frame, viewpoints and seed.
    stepper = torch.jit.load(str(run / meta["stepper"]["file"]))
    with open_bundle(out / "bundle") as b:
        r = DynamicRenderer(b)
        views = read_cameras(out / "cameras.json")
        vv = np.stack([r.view_of(v) for v in views])
        first = rgba_tensor(r.first, r.size)
        torch.manual_seed(SEED)
        x = rollout(stepper, first, torch.from_numpy(np.concatenate([r.first_view[None], vv]))[None].float())[0]
        ref = to_u8(x.permute(0, 2, 3, 1).numpy())
        rows = []
        for k, v in enumerate(views):
            got = read_rgba(out / "renders" / v.name).astype(np.float32) / 255
            want = r.warp(ref[k], v).astype(np.float32) / 255
            rows.append(psnr_from_mse(float(((got - want) ** 2).mean())))
    t = time.perf_counter()
    checks = verify_bundle(out / "bundle")
    verify_s = time.perf_counter() - t
    return {"run": str(run), "bundle_seconds": round(bundle_s, 1), "proxy": m.proxy_mesh,
            "proxy_vs_truth": hull_iou(m, out / "bundle", times, seed, res) if seed is not None else None,
            "renders": len(rows), "render_seconds": round(render_s, 2),
            "psnr_bundle_vs_run_min": round(min(rows), 2) if all(map(math.isfinite, rows)) else None,
            "verify_seconds": round(verify_s, 1), "verify": checks,
            "flipped_byte": flipped_byte_caught(out / "bundle", out)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("part", choices=["static", "dynamic"])
    ap.add_argument("run", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--capture", type=Path, default=None, help="synthetic capture whose ground truth is the shape")
    ap.add_argument("--seed", type=int, default=None,
                    help="seed of the synthetic object: bench_plenoctree's static one (default 0), or "
                         "synth.crops.synthetic_crops' dynamic toy (dynamic: IoU of the visual hull only when given)")
    ap.add_argument("--res", type=int, default=128, help="voxels per axis for the IoU")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    res = (bench_static(a.run, a.out, a.capture, a.seed or 0, a.res) if a.part == "static"
           else bench_dynamic(a.run, a.out, a.seed, a.res))
    return emit(res, a.json)


if __name__ == "__main__":
    sys.exit(main())
