"""PlenOctree benchmarks: quality on NeRF-synthetic lego, fox and a synthetic object, render
speed and size of the baked tree (figures in docs/results.md).

Each part evaluates a run folder written by ``dbb-train plenoctree`` (train it first, one
benchmark at a time so timings do not overlap), or trains one itself:

    python bench/bench_plenoctree.py lego RUN            # held-out PSNR (white) + SSIM, speed, size
    python bench/bench_plenoctree.py fox RUN             # held-out PSNR on the 17 listed frames
    python bench/bench_plenoctree.py synth OUT --minutes 10   # synthetic object, novel views
    python bench/bench_plenoctree.py capture DATASET --capture CAPTURE --run RUN --minutes 10
        # a synthetic capture through preprocess: held-out crops scored against the truth
        # (--steps N: fixed steps; --truth DIR: train on crops re-made from the ground truth)
    python bench/bench_plenoctree.py ceiling CAPTURE     # crops of the footage with the true coverage,
        # through the true cameras, against the truth: what the footage allows any matte
    python bench/bench_plenoctree.py crops DATASET --capture CAPTURE   # the crops themselves against the truth
    python bench/bench_plenoctree.py carve DATASET --capture CAPTURE   # what carving removes, against the truth
    python bench/bench_plenoctree.py speed RUN           # render speed and size of the tree only
    python bench/bench_plenoctree.py novel RUN --capture CAPTURE   # novel views at 128 and 256 px
        # along the path, between the frames, against the synthetic truth
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from common import emit  # bench/ is the script folder: on sys.path

from dbb_capture.core.metrics import psnr_from_mse
from dbb_capture.datasets.records import Frame, ObjectVolume
from dbb_capture.datasets.transforms import load_dataset, write_transforms
from dbb_capture.geometry.cameras import Intrinsics, scaled_intrinsics
from dbb_capture.geometry.transforms import look_at
from dbb_capture.octree.render import TreeRenderer
from dbb_capture.static.rays import frame_tensors
from dbb_capture.static.render import render_image
from dbb_capture.static.run import (
    RunConfig,
    evaluate_views,
    load_run,
    mean_of,
    split_frames,
    train_run,
)
from dbb_capture.static.train import TrainState

FOX_HELDOUT = ("0005", "0016", "0017", "0024", "0032", "0051", "0068", "0071", "0075", "0083", "0087",
               "0088", "0093", "0099", "0104", "0106", "0113")


def render_speed(renderer: TreeRenderer, c2w: np.ndarray, base: Intrinsics, size: int, repeats: int) -> float:
    """Frames per second rendering straight RGBA at size x size (same field of view as ``base``)."""
    intr = scaled_intrinsics(base, base.width / size)
    renderer.render(c2w, intr)                               # warm up
    t = time.perf_counter()
    for _ in range(repeats):
        renderer.render(c2w, intr)
    return repeats / (time.perf_counter() - t)


def bench_lego(run_dir: Path, repeats: int) -> dict:
    run = load_run(run_dir)
    ds = load_dataset(Path(run.record.dataset))
    test = split_frames(ds, RunConfig(holdout_every=8)).test
    tree = run.tree()
    r = TreeRenderer(tree)
    rows = evaluate_views(r, test, run.record.training.downscale)
    f = test[0]
    return {
        "run": str(run_dir), "train_minutes": run.record.training.seconds / 60,
        "steps": run.record.training.steps, "final_lattice": run.record.final_res,
        "heldout_views": len(test), "psnr_white": mean_of(rows, "psnr_white"),
        "ssim_white": mean_of(rows, "ssim_white"),
        "tree_mb": run.tree_path.stat().st_size / 1e6, "tree_depth": tree.depth_limit,
        "fps_256": render_speed(r, f.c2w, f.intr, 256, repeats),
        "fps_800": render_speed(r, f.c2w, f.intr, 800, max(1, repeats // 4)),
        "threads": torch.get_num_threads(),
    }


def bench_speed(run_dir: Path, repeats: int) -> dict:
    """Render speed and size of a run's tree alone (first held-out camera of its dataset)."""
    run = load_run(run_dir)
    ds = load_dataset(Path(run.record.dataset))
    test = split_frames(ds, RunConfig(holdout_every=8)).test
    r = TreeRenderer(run.tree())
    f = test[0]
    return {"run": str(run_dir), "tree_mb": run.tree_path.stat().st_size / 1e6,
            "fps_256": render_speed(r, f.c2w, f.intr, 256, repeats),
            "fps_800": render_speed(r, f.c2w, f.intr, 800, max(1, repeats // 4)),
            "threads": torch.get_num_threads()}


def bench_fox(run_dir: Path) -> dict:
    """Held-out PSNR of the scene field (fox is a scene: the tree holds only the inner sphere)."""
    run = load_run(run_dir)
    ds = load_dataset(Path(run.record.dataset))
    test = split_frames(ds, RunConfig(holdout_names=FOX_HELDOUT)).test
    st = TrainState.load(run.checkpoint_path, torch.device("cpu"))
    ps = []
    for f in test:
        o, d, rgba = frame_tensors(f, run.record.training.downscale)
        img = render_image(st.field, torch.from_numpy(o), torch.from_numpy(d), (0.0, 0.0, 0.0))
        ps.append(psnr_from_mse(float(((img - rgba[..., :3]) ** 2).mean())))
    return {"run": str(run_dir), "train_minutes": run.record.training.seconds / 60,
            "steps": run.record.training.steps, "heldout_views": len(test),
            "psnr_heldout_field": float(np.mean(ps)), "per_view": dict(zip([f.name for f in test], ps)),
            "tree_heldout_white_report": run.record.metrics.get("mean_psnr_tree_white")}


def synth_dataset(out: Path, n_train: int = 60, n_test: int = 12, size: int = 128, seed: int = 0) -> Path:
    """Posed 128 px RGBA views of the synthetic static object rendered from its ground truth,
    cameras on the synthetic camera path's azimuth/elevation/distance ranges, each looking at
    the object's centre like a crop camera. Test views are novel poses (interleaved azimuths)."""
    import cv2

    from dbb_capture.capture.board import BoardSpec
    from dbb_capture.synth.objects import make_object
    from dbb_capture.synth.render import render_object_rgba
    from dbb_capture.synth.scene import SynthConfig

    cfg = SynthConfig(seed=seed)
    model = make_object("static", BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100"), np.random.default_rng(seed))
    c, r = model.bounding_sphere(np.array([0.0]))
    rng = np.random.default_rng(seed + 7)
    out.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n_train + n_test):
        test = i >= n_train
        az = math.radians(rng.uniform(*cfg.azimuth_range_deg) - 90)
        el = math.radians(rng.uniform(*cfg.elevation_range_deg))
        dist = rng.uniform(*cfg.distance_range_m)
        eye = c + dist * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), -math.sin(el)])
        c2w = look_at(eye, c, np.array([0, 0, -1.0]))
        f = 0.5 * size * dist / (1.15 * r) * math.sqrt(1 - (1.15 * r / dist) ** 2)   # sphere fills the crop
        intr = Intrinsics(size, size, f, f, (size - 1) / 2, (size - 1) / 2)
        p = out / f"{i:04d}.png"
        cv2.imwrite(str(p), cv2.cvtColor(render_object_rgba(model, intr, c2w, 0.0), cv2.COLOR_RGBA2BGRA))
        frames.append(Frame(f"{i:04d}", p, c2w, intr, "test" if test else "train"))
    write_transforms(out / "crops.json", frames, ObjectVolume(tuple(float(v) for v in c), float(r) * 1.1))
    return out


def bench_synth(out: Path, minutes: float) -> dict:
    data = synth_dataset(out / "dataset")
    t = time.perf_counter()
    run = train_run(data, out / "run", RunConfig(minutes=minutes), overwrite=True)
    wall = time.perf_counter() - t
    ds = load_dataset(data)
    test = ds.split("test")
    rows = evaluate_views(TreeRenderer(run.tree()), test, 1.0, ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)))
    return {"train_minutes": run.record.training.seconds / 60, "wall_minutes_incl_bake": wall / 60,
            "steps": run.record.training.steps, "heldout_views": len(test),
            "psnr_black": mean_of(rows, "psnr_black"), "psnr_white": mean_of(rows, "psnr_white"),
            "ssim_white": mean_of(rows, "ssim_white"), "tree_mb": run.tree_path.stat().st_size / 1e6}


def novel_cameras(frames: list[Frame], center: np.ndarray, radius: float, up: np.ndarray, size: int,
                  count: int = 16, fill: float = 0.9) -> list[tuple[np.ndarray, Intrinsics]]:
    """``count`` cameras at poses no frame was taken from, spread along the capture's path: each
    between two consecutive frames (the mean of their directions from the object centre and of
    their distances), looking at the centre with the sphere (``center`` (3,), ``radius``) filling
    ``fill`` of ``size`` pixels, like a crop camera. OpenCV camera-to-world (4, 4) and intrinsics."""
    from dbb_capture.crops.camera import facing_camera

    order = sorted(frames, key=lambda f: (f.time if f.time is not None else 0.0, f.name))
    eyes = np.stack([f.c2w[:3, 3] for f in order])
    cams = []
    for i in np.linspace(0, len(order) - 2, count).round().astype(int):
        a, b = eyes[i] - center, eyes[i + 1] - center
        d = a / np.linalg.norm(a) + b / np.linalg.norm(b)
        eye = center + d / np.linalg.norm(d) * 0.5 * (np.linalg.norm(a) + np.linalg.norm(b))
        cams.append(facing_camera(eye, center, radius, up, size, fill))
    return cams


def bench_novel(run_dir: Path, capture: Path, sizes: tuple[int, ...] = (128, 256), count: int = 16) -> dict:
    """A run of a synthetic static capture scored on novel views (:func:`novel_cameras`) at each
    of ``sizes`` px against the object alone rendered from the ground truth, on black and white."""
    from dbb_capture.synth.capture import load_ground_truth
    from dbb_capture.synth.render import render_object_rgba

    run = load_run(run_dir)
    ds = load_dataset(Path(run.record.dataset))
    doc = json.loads(ds.source.read_text())
    up = np.asarray(doc.get("up", [0.0, 0.0, -1.0]), np.float64)
    center, radius = np.asarray(run.volume.center, np.float64), float(run.volume.radius)
    _, _, model = load_ground_truth(capture)
    r = TreeRenderer(run.tree())
    out = {"run": str(run_dir), "crop_size": doc.get("crop_size"), "tree_depth": run.record.tree.depth_limit,
           "final_lattice": run.record.final_res, "tree_mb": run.tree_path.stat().st_size / 1e6,
           "steps": run.record.training.steps, "views": count,
           "report": {k: v.get("mean_psnr_tree_white") for k, v in run.record.metrics.get("sets", {}).items()}}
    for size in sizes:
        rows, parts = [], []
        for c2w, intr in novel_cameras(ds.frames, center, radius, up, size, count, doc.get("crop_fill", 0.9)):
            gt = render_object_rgba(model, intr, c2w, 0.0).astype(np.float32) / 255
            img = r.render(c2w, intr)
            rows.append(psnr_on_backgrounds(img, gt))
            parts.append(error_parts(img, gt))
        out[f"px{size}"] = {"psnr_black": mean_of(rows, "black"), "psnr_white": mean_of(rows, "white"),
                            "min_black": min(x["black"] for x in rows), "min_white": min(x["white"] for x in rows),
                            "per_view_white": [round(x["white"], 2) for x in rows], "error": summarize_parts(parts)}
    return out


def truth_crops(dataset: Path, capture: Path, out: Path) -> Path:
    """The dataset's crops re-made from the synthetic capture's ground truth: the object alone
    rendered through every crop camera at its time (exact alpha), same cameras and split.
    Training on it measures the ceiling the field reaches with perfect mattes."""
    import cv2

    from dbb_capture.synth.capture import load_ground_truth
    from dbb_capture.synth.render import render_object_rgba

    ds = load_dataset(dataset)
    _, _, model = load_ground_truth(capture)
    (out / "crops").mkdir(parents=True, exist_ok=True)
    frames = []
    for f in ds.frames:
        p = out / "crops" / f"{f.name}.png"
        rgba = render_object_rgba(model, f.intr, f.c2w, float(f.time or 0.0))
        cv2.imwrite(str(p), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
        frames.append(Frame(f.name, p, f.c2w, f.intr, f.split, time=f.time))
    write_transforms(out / "crops.json", frames, ds.volume)
    return out


def footage_ceiling(capture: Path, size: int = 128, fill: float = 0.9, test_fraction: float = 0.2,
                    every: int = 8) -> dict:
    """The footage's own ceiling, through the capture's *true* cameras (no pose error): every
    frame's crop camera (:func:`~dbb_capture.crops.camera.crop_camera`, as preprocess makes it) cut
    from the video (:func:`~dbb_capture.crops.camera.cut_crop`, the same warp), alpha = the true
    full-frame coverage (ground-truth masks) through the same warp, the colour as observed or
    taken out of the true room (the scene rendered without the object through the crop camera,
    as a perfect matte would); scored against the object alone rendered through the crop camera,
    on black and white, for the crops of the time split's test part, the every-n-th crops and all."""
    import cv2
    from bench_preprocess import synth_scene  # bench/ is the script folder: on sys.path

    from dbb_capture.capture.footage import capture_footage
    from dbb_capture.crops.camera import crop_camera, cut_crop
    from dbb_capture.crops.matte import straight_rgba
    from dbb_capture.crops.sequences import split_by_time
    from dbb_capture.geometry.conventions import opencv_from_opengl
    from dbb_capture.synth.capture import load_ground_truth
    from dbb_capture.synth.render import Renderer, render_object_rgba

    intr, cams, model = load_ground_truth(capture)
    room_scene = synth_scene(capture).without_object()
    obj = json.loads((capture / "object.json").read_text())
    centre, radius, up = np.array(obj["center"]), float(obj["radius"]), np.array([0.0, 0.0, -1.0])
    video = cams["video"]
    times = np.array([fr["time"] for fr in video])
    test_time = split_by_time(times, test_fraction) == "test"
    rows = []
    for img in capture_footage(capture).read(range(len(video))):
        fr = video[img.index]
        c2w = opencv_from_opengl(np.array(fr["transform_matrix"]))
        cam = crop_camera(c2w, intr, centre, radius, up, size, fill)
        observed, _ = cut_crop(img.image, cam, intr, c2w)
        mask = cv2.imread(str(capture / "ground_truth" / "masks" / f"{img.index:05d}.png"), cv2.IMREAD_GRAYSCALE)
        alpha = cut_crop(mask[..., None], cam, intr, c2w)[0].reshape(size, size)
        room = Renderer(cam.intr, 2).render(room_scene, cam.c2w, fr["time"])[0]
        room = np.clip(np.round(room * 255), 0, 255).astype(np.uint8)
        gt = render_object_rgba(model, cam.intr, cam.c2w, fr["time"]).astype(np.float32) / 255
        row = {"index": img.index}
        for tag, rgba in (("raw", np.concatenate([observed, alpha[..., None]], -1)),
                          ("unmixed", straight_rgba(observed, room, alpha.astype(np.float32) / 255))):
            c = rgba.astype(np.float32) / 255
            row.update({f"{tag}_{key}": v for key, v in psnr_on_backgrounds(c, gt).items()})
            row[f"{tag}_parts"] = error_parts(c, gt)
        rows.append(row)
    out = {"capture": str(capture), "size": size, "crops": len(rows)}
    for name, sel in (("all", np.ones(len(rows), bool)), ("test_time", test_time),
                      (f"every_{every}", np.arange(len(rows)) % every == 0)):
        picked = [r for r, s in zip(rows, sel) if s]
        out[name] = {"views": len(picked)}
        for tag in ("raw", "unmixed"):
            out[name][tag] = {"psnr_black": mean_of(picked, f"{tag}_black"),
                              "psnr_white": mean_of(picked, f"{tag}_white"),
                              "error": summarize_parts([r[f"{tag}_parts"] for r in picked])}
    return out


def carve_check(dataset: Path, capture: Path, res: int = 128, shares: tuple[float, ...] = (0.1, 0.2, 0.3),
                min_views: int = 3) -> list[dict]:
    """What carving (:func:`~dbb_capture.static.rays.carve_mask`) does on a synthetic capture's
    dataset, from the mattes of its training crops: the share of the object sphere's lattice
    points (``res`` per axis) carved, the points inside the true object carved (ought to be
    none), and the share of the points further than 1.5 cells from the object that stay."""
    from dbb_capture.static.rays import build_ray_bank, carve_mask
    from dbb_capture.synth.capture import load_ground_truth

    ds = load_dataset(dataset)
    vol = ds.volume
    bank = build_ray_bank(ds.split("train"), 1, vol)
    _, _, model = load_ground_truth(capture)
    ax = (np.arange(res) + 0.5) / res * 2 - 1
    x = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    pts = x[(x ** 2).sum(-1) <= 1] * vol.radius + np.asarray(vol.center)
    cell = 2 * vol.radius / res
    inside, near = np.zeros(len(pts), bool), np.zeros(len(pts), bool)
    for c, rot, e in model.posed(0.0):
        inside |= np.linalg.norm((pts - c) @ rot / np.asarray(e.radii), axis=1) <= 1
        near |= np.linalg.norm((pts - c) @ rot / (np.asarray(e.radii) + 1.5 * cell), axis=1) <= 1
    rows = []
    for share in shares:
        cut = carve_mask(bank.views, pts, cell, share, min_views)
        rows.append({"share": share, "min_views": min_views, "carved": float(cut.mean()),
                     "object_points": int(inside.sum()), "object_points_carved": int(cut[inside].sum()),
                     "outside_kept": float((~cut[~near]).mean())})
    return rows


def resplit_crops(dataset: Path, out: Path, every: int) -> Path:
    """A copy of the dataset's ``crops.json`` in ``out`` (image paths made absolute) where every
    ``every``-th crop (0, every, ...) is held out instead of the last 20% of the capture's time:
    novel views between training views, as NeRF benchmarks hold out (lego: every 8th), rather
    than views past the end of the training path."""
    from dbb_capture.datasets.transforms import find_dataset_file

    src = find_dataset_file(dataset)
    doc = json.loads(src.read_text())
    for i, fr in enumerate(doc["frames"]):
        fr["split"] = "test" if i % every == 0 else "train"
        for key in ("file_path", "mask_path", "observed_path", "background_path"):
            if fr.get(key):
                fr[key] = str((src.parent / fr[key]).resolve())
    out.mkdir(parents=True, exist_ok=True)
    (out / "crops.json").write_text(json.dumps(doc))
    return out


def error_parts(img_rgba: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """Where a render's error on white lies, per pixel sums over one view (divide by pixels):
    squared error on white where the truth's alpha is 0 (< 0.01: "room"), 1 (> 0.99: "core")
    and between ("rim"), and of room and core the part within 1.5 px of the outline
    ("room_edge", "core_edge"); squared alpha error; squared premultiplied-colour error (= on black);
    the render's alpha summed over the room and its transparency over the core.
    ``img_rgba`` / ``gt`` straight RGBA (H, W, 4) in [0, 1]."""
    import cv2

    a, at = img_rgba[..., 3], gt[..., 3]
    pm, pmt = img_rgba[..., :3] * a[..., None], gt[..., :3] * at[..., None]
    se = (((pm + 1 - a[..., None]) - (pmt + 1 - at[..., None])) ** 2).mean(-1)
    room, core = at < 0.01, at > 0.99
    rim = ~room & ~core
    # The outline's own band: room and core pixels within 1.5 px of the other regions (the
    # "_edge" parts are shares of "room" and "core", not further regions).
    def edge(m: np.ndarray) -> np.ndarray:
        return m & (cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, 3) < 1.5)
    return {"px": float(a.size), "px_room": float(room.sum()), "px_core": float(core.sum()),
            "se_white_room": float(se[room].sum()), "se_white_core": float(se[core].sum()),
            "se_white_rim": float(se[rim].sum()), "se_white_room_edge": float(se[edge(room)].sum()),
            "se_white_core_edge": float(se[edge(core)].sum()), "se_alpha": float(((a - at) ** 2).sum()),
            "se_premult": float(((pm - pmt) ** 2).mean(-1).sum()), "alpha_on_room": float(a[room].sum()),
            "holes_in_core": float((1 - a[core]).sum())}


def summarize_parts(parts: list[dict[str, float]]) -> dict[str, float]:
    """:func:`error_parts` summed over views: MSE on white split by region (they add up to the
    whole), alpha and premultiplied-colour MSE, mean alpha over the room, mean 1 - alpha over the core."""
    t = {k: sum(p[k] for p in parts) for k in parts[0]}
    n = t["px"]
    out = {f"mse_white_{k}": t[f"se_white_{k}"] / n for k in ("room", "core", "rim", "room_edge", "core_edge")}
    out |= {"mse_alpha": t["se_alpha"] / n, "mse_premult": t["se_premult"] / n,
            "mean_alpha_on_room": t["alpha_on_room"] / max(t["px_room"], 1),
            "mean_holes_in_core": t["holes_in_core"] / max(t["px_core"], 1),
            "share_px_room": t["px_room"] / n, "share_px_core": t["px_core"] / n}
    return out


def psnr_on_backgrounds(rgba: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """PSNR (dB) of straight RGBA ``rgba`` (H, W, 4) float 0..1 against the truth ``gt`` (same),
    both composited on black and on white: {"black": ..., "white": ...}."""
    out = {}
    for key, bg in (("black", 0.0), ("white", 1.0)):
        t = gt[..., :3] * gt[..., 3:] + (1 - gt[..., 3:]) * bg
        m = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]) * bg
        out[key] = psnr_from_mse(float(((m - t) ** 2).mean()))
    return out


def score_crops(dataset: Path, capture: Path, every: int = 8) -> dict:
    """The dataset's crops themselves (no training) against the capture's ground truth: PSNR on
    black and white (the object alone rendered through each crop camera at its time) and where
    the error lies (:func:`error_parts`), for the held-out crops of both protocols (the time
    split's test part, every ``every``-th crop), the time split's training crops and all."""
    from dbb_capture.synth.capture import load_ground_truth
    from dbb_capture.synth.render import render_object_rgba

    frames = load_dataset(dataset).frames
    _, _, model = load_ground_truth(capture)
    rows, parts = [], []
    for f in frames:
        gt = render_object_rgba(model, f.intr, f.c2w, float(f.time or 0.0)).astype(np.float32) / 255
        _, _, crop = frame_tensors(f, 1.0)
        rows.append({f"psnr_{key}": v for key, v in psnr_on_backgrounds(crop, gt).items()})
        parts.append(error_parts(crop, gt))
    out = {"dataset": str(dataset), "crops": len(frames)}
    split = np.array([f.split for f in frames])
    for name, sel in (("test_time", split == "test"), ("train_time", split == "train"),
                      (f"every_{every}", np.arange(len(frames)) % every == 0), ("all", np.ones(len(frames), bool))):
        picked = np.flatnonzero(sel)
        if len(picked):
            out[name] = {"views": len(picked), "psnr_black": mean_of([rows[i] for i in picked], "psnr_black"),
                         "psnr_white": mean_of([rows[i] for i in picked], "psnr_white"),
                         "error": summarize_parts([parts[i] for i in picked])}
    return out


def bench_capture(dataset: Path, capture: Path, run_dir: Path, minutes: float | None, res_max: int | None,
                  train: bool, field: dict | None = None, steps: int | None = None, truth: Path | None = None,
                  holdout_every: int = 0, prune_weight: float | None = None, depth: int | None = None) -> dict:
    """Train on a preprocess dataset of a synthetic capture (crops.json) and score the tree on
    the held-out crops (the dataset's test split) against the capture's ground truth: the
    object alone rendered through each crop camera at its time, on black and on white. Also
    against the preprocess crops themselves (their alpha is a matte, not the truth), and where
    the error lies (:func:`error_parts`) for the tree and for the crops.
    ``field``: FieldConfig settings to change from the defaults; ``steps``: a fixed number of
    steps instead of (or besides) ``minutes``; ``truth``: train instead on the crops re-made
    from the ground truth in this folder (:func:`truth_crops`), the ceiling of perfect mattes;
    ``holdout_every``: hold out every n-th crop instead of the dataset's split (:func:`resplit_crops`);
    ``prune_weight``: the bake's weight pruning (None: the default); ``depth``: the octree's
    (None: matching the lattice)."""
    from dbb_capture.static.field import FieldConfig
    from dbb_capture.synth.capture import load_ground_truth
    from dbb_capture.synth.render import render_object_rgba

    if holdout_every:
        dataset = resplit_crops(dataset, run_dir.parent / f"{run_dir.name}.split{holdout_every}", holdout_every)
    data = truth_crops(dataset, capture, truth) if truth is not None else dataset
    if train:
        fc = FieldConfig(**({"res_max": res_max, "res_start": min(32, res_max or 32)} | (field or {})))
        rc = RunConfig(minutes=minutes, steps=steps, depth=depth)
        train_run(data, run_dir, rc if prune_weight is None else replace(rc, prune_weight=prune_weight), fc,
                  overwrite=True)
    run = load_run(run_dir)
    ds = load_dataset(dataset)
    test = ds.split("test")
    _, _, model = load_ground_truth(capture)
    r = TreeRenderer(run.tree())
    rows, parts, crop_parts = [], [], []
    for f in test:
        gt = render_object_rgba(model, f.intr, f.c2w, float(f.time or 0.0)).astype(np.float32) / 255
        _, _, crop = frame_tensors(f, 1.0)
        row = {"frame": f.name}
        for key, bg in (("black", (0.0, 0.0, 0.0)), ("white", (1.0, 1.0, 1.0))):
            img = r.render(f.c2w, f.intr, bg)
            b = np.asarray(bg, np.float32)
            truth_img = gt[..., :3] * gt[..., 3:] + (1 - gt[..., 3:]) * b
            mat = crop[..., :3] * crop[..., 3:] + (1 - crop[..., 3:]) * b
            row[f"psnr_truth_{key}"] = psnr_from_mse(float(((img - truth_img) ** 2).mean()))
            row[f"psnr_crop_{key}"] = psnr_from_mse(float(((img - mat) ** 2).mean()))
            row[f"psnr_crop_vs_truth_{key}"] = psnr_from_mse(float(((mat - truth_img) ** 2).mean()))
        rows.append(row)
        parts.append(error_parts(r.render(f.c2w, f.intr), gt))
        crop_parts.append(error_parts(crop, gt))
    out = {"run": str(run_dir), "dataset": str(data), "train_minutes": run.record.training.seconds / 60,
           "steps": run.record.training.steps, "final_lattice": run.record.final_res,
           "heldout_views": len(test)}
    for k in rows[0] if rows else ():
        if k != "frame":
            out[k] = mean_of(rows, k)
    if parts:
        out["tree_error"] = summarize_parts(parts)
        out["crop_error"] = summarize_parts(crop_parts)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("part", choices=["lego", "fox", "synth", "speed", "capture", "ceiling", "carve", "crops", "novel"])
    ap.add_argument("path", type=Path,
                    help="run folder (lego, fox), output folder (synth), dataset (capture, carve, crops) or capture (ceiling)")
    ap.add_argument("--minutes", type=float, default=None, help="training budget (default 10 without --steps)")
    ap.add_argument("--capture", type=Path, help="capture, carve, crops: the synthetic capture (its ground_truth/)")
    ap.add_argument("--run", type=Path, help="capture: run folder to write (or read with --no-train)")
    ap.add_argument("--res-max", type=int, default=None,
                    help="capture: finest lattice (default: dbb-train's, by the views); carve: the lattice (default 128)")
    ap.add_argument("--no-train", action="store_true", help="capture: score an existing run")
    ap.add_argument("--steps", type=int, default=None,
                    help="capture: train this many steps (alone unless --minutes is given too)")
    ap.add_argument("--prune-weight", type=float, default=None,
                    help="capture: the bake's weight pruning (default: dbb-train's)")
    ap.add_argument("--depth", type=int, default=None, help="capture: octree depth (default: match the lattice)")
    ap.add_argument("--holdout-every", type=int, default=0,
                    help="capture: hold out every n-th crop instead of the last 20%% of the capture's time")
    ap.add_argument("--truth", type=Path, default=None,
                    help="capture: train on the crops re-made from the ground truth, written to this folder")
    ap.add_argument("--field", type=json.loads, default=None,
                    help='capture: FieldConfig settings to change, JSON, e.g. \'{"tv_density": 1e-4}\'')
    ap.add_argument("--crop-size", type=int, default=128, help="ceiling: crop side in pixels")
    ap.add_argument("--repeats", type=int, default=8)
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = ap.parse_args(argv)
    if a.part == "lego":
        res = bench_lego(a.path, a.repeats)
    elif a.part == "speed":
        res = bench_speed(a.path, a.repeats)
    elif a.part == "fox":
        res = bench_fox(a.path)
    elif a.part == "capture":
        if a.capture is None or a.run is None:
            ap.error("capture needs --capture and --run")
        res = bench_capture(a.path, a.capture, a.run, a.minutes,
                            a.res_max, not a.no_train, a.field, a.steps, a.truth, a.holdout_every, a.prune_weight,
                            a.depth)
    elif a.part == "ceiling":
        res = footage_ceiling(a.path, a.crop_size)
    elif a.part == "crops":
        if a.capture is None:
            ap.error("crops needs --capture")
        res = score_crops(a.path, a.capture)
    elif a.part == "novel":
        if a.capture is None:
            ap.error("novel needs --capture")
        res = bench_novel(a.path, a.capture)
    elif a.part == "carve":
        if a.capture is None:
            ap.error("carve needs --capture")
        res = carve_check(a.path, a.capture, a.res_max or 128)
    else:
        res = bench_synth(a.path, a.minutes or 10.0)
    return emit(res, a.json)


if __name__ == "__main__":
    sys.exit(main())
