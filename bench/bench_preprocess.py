"""Background removal and crops against synthetic ground truth, and per-frame throughput.

Quality (``quality``): runs ``dbb-capture preprocess`` on synthetic captures (the sample
captures by default: static and dynamic, 640x480, with clean plates), once with the clean
plate and once without (``--no-clean-plate``), then scores every crop against the truth:
- alpha IoU (alpha > 50%) with the true object coverage (> 50%) resampled into the crop exactly
  as the footage was (the estimated camera, the same supersampling): the matte's own error,
  pixel for pixel (median over frames);
- the same against the coverage mapped through the *true* camera (pose errors move it);
- where the true object centre lands in the crop (px, scaled to a 64 px crop);
- the true sphere's projected radius across frames (max deviation from the median, %);
- the angle between the object's true up and the crop's up (degrees).
The crop geometry is scored with the truth mapped through the *estimated* camera, so pose
errors count.

Speed (``speed``): a 1920x1440 capture with a 15 s clean plate; times the background stage
(pose the plate, cut training crops, plane sweep, train) and then the per-frame work on the
object video: detect + pose, crop, background render, matte (one process, and the rate two
processes would give since frames are independent).

``quality --rematte`` crops and mattes the datasets already in ``--work`` again with the current
code (their poses and background fields kept, both matte passes as preprocess runs them) and
scores the first pass alone and both passes: the matte compared on the same fields, whatever
the machine's load gave the time-budgeted field training.

Error budget (``budget``): on synthetic captures, through their true cameras and without any
trained field, what resampling the footage costs (its true coverage cut through the crop warp
against the coverage through the crop camera), the matte's own ceiling (perfect footage: the
scene rendered through the crop camera without noise or compression, against the room rendered
there without the object) and the matte of the real footage against that perfect room (what the
footage costs; the rest of a ``quality`` figure with a clean plate is the background field's).
The crops are cached in ``--work`` (``NAME-budget.npz``).

    .venv/bin/python bench/bench_preprocess.py quality --work out/bench/pre
    .venv/bin/python bench/bench_preprocess.py budget --work out/bench/budget --captures sample_data/dynamic
    .venv/bin/python bench/bench_preprocess.py quality --work out/bench/pre --rematte
    .venv/bin/python bench/bench_preprocess.py quality --work out/bench/quality --steps 1000
    .venv/bin/python bench/bench_preprocess.py speed --work out/bench/pre
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from dbb_capture.crops.camera import crop_maps, cut_crop
from dbb_capture.geometry.cameras import Intrinsics, project_points
from dbb_capture.geometry.conventions import opencv_from_opengl
from dbb_capture.geometry.conventions import centre_from_corner_px
from dbb_capture.geometry.rays import camera_rays

REPO = Path(__file__).resolve().parents[1]


def _cam_from_frame(fr: dict):
    from dbb_capture.crops.camera import CropCamera
    from dbb_capture.geometry.viewpoint import Viewpoint

    # The file's principal point has the corner origin (the contract's); Intrinsics are OpenCV's.
    intr = Intrinsics(fr["w"], fr["h"], fr["fl_x"], fr["fl_y"], centre_from_corner_px(fr["cx"]), centre_from_corner_px(fr["cy"]))
    vp = Viewpoint(**fr["viewpoint"])
    return CropCamera(intr, opencv_from_opengl(np.array(fr["transform_matrix"])), vp, 0.0)


def to_crop(uv: np.ndarray, intr: Intrinsics, c2w: np.ndarray, cam) -> np.ndarray:
    """Source pixels (N, 2) of a camera (``intr`` with distortion, OpenCV ``c2w``) -> crop pixels (N, 2)."""
    d = camera_rays(intr, uv) @ c2w[:3, :3].T @ cam.c2w[:3, :3]
    return np.stack([cam.intr.fx * d[:, 0] / d[:, 2] + cam.intr.cx, cam.intr.fy * d[:, 1] / d[:, 2] + cam.intr.cy], 1)


def score(capture: Path, dataset: Path) -> dict:
    gt_intr = Intrinsics.load(capture / "ground_truth" / "camera.json")
    gt = json.loads((capture / "ground_truth" / "cameras.json").read_text())["video"]
    obj = json.loads((capture / "object.json").read_text())
    center, radius = np.array(obj["center"]), obj["radius"]
    up = np.array([0.0, 0.0, -1.0])  # synth lays the board face up with the cameras above (-z)
    est_intr = Intrinsics.load(dataset / "camera.json")
    crops = json.loads((dataset / "crops.json").read_text())
    ious, ious_true, centre_px, radii, up_deg = [], [], [], [], []
    for fr in crops["frames"]:
        cam = _cam_from_frame(fr)
        i = fr["source_frame"]
        c2w_true = opencv_from_opengl(np.array(gt[i]["transform_matrix"]))
        size = cam.intr.width
        mask = cv2.imread(str(capture / "ground_truth" / "masks" / f"{i:05d}.png"), cv2.IMREAD_GRAYSCALE)
        mx, my = crop_maps(cam, gt_intr, c2w_true, 1)
        truth_true = cv2.remap(mask, mx, my, cv2.INTER_LINEAR) > 127
        # Pixels of the real image map to the crop through the camera preprocessing estimated.
        src = _estimated_c2w(dataset, fr)
        cam_px = replace(cam, window_px=size * 0.5 * (est_intr.fx + est_intr.fy) / cam.intr.fx)
        truth = cut_crop(mask[..., None], cam_px, est_intr, src)[0].reshape(size, size) > 127
        alpha = cv2.imread(str(dataset / fr["file_path"]), cv2.IMREAD_UNCHANGED)[..., 3] > 127
        ious.append((truth & alpha).sum() / max((truth | alpha).sum(), 1))
        ious_true.append((truth_true & alpha).sum() / max((truth_true | alpha).sum(), 1))
        uv_true = project_points(np.stack([center, center + 0.02 * up]), c2w_true, gt_intr)
        p = to_crop(uv_true, est_intr, src, cam)
        c = (size - 1) / 2
        centre_px.append(float(np.linalg.norm(p[0] - c)) * 64 / size)
        v = p[1] - p[0]
        up_deg.append(abs(math.degrees(math.atan2(v[0], -v[1]))))
        D = float(np.linalg.norm(c2w_true[:3, 3] - center))
        radii.append(cam.intr.fx * math.tan(math.asin(radius / D)))
    radii = np.array(radii)
    return {"crops": len(ious), "iou_median": float(np.median(ious)), "iou_p10": float(np.percentile(ious, 10)),
            "iou_true_cam_median": float(np.median(ious_true)),
            "centre_px64_median": float(np.median(centre_px)), "centre_px64_max": float(np.max(centre_px)),
            "radius_dev_pct": float(np.abs(radii / np.median(radii) - 1).max() * 100),
            "up_deg_median": float(np.median(up_deg)), "up_deg_max": float(np.max(up_deg))}


_TRANSFORMS: dict = {}


def _estimated_c2w(dataset: Path, fr: dict) -> np.ndarray:
    """The estimated pose of the frame a crop was cut from (transforms.json of the dataset)."""
    if dataset not in _TRANSFORMS:
        tf = json.loads((dataset / "transforms.json").read_text())
        _TRANSFORMS[dataset] = {round(f["time"], 4): opencv_from_opengl(np.array(f["transform_matrix"]))
                                for f in tf["frames"]}
    return _TRANSFORMS[dataset][round(fr["time"], 4)]


def both_passes(crops: list, times: np.ndarray, fill: float, cfg, counts: np.ndarray | None = None) -> list[np.ndarray]:
    """Straight RGBA (S, S, 4) uint8 (the output size) of every first-pass crop (:class:`~dbb_capture.crops.camera.ObjectCrop`,
    in time order, ``times`` (N,) s) after the second pass, as the crops stage runs it: the
    capture's statistics (``counts``: summed sure object colours where a prediction was a guess),
    matte again, temporal median over neighbouring frames."""
    from dbb_capture.crops.matte import capture_matte
    from dbb_capture.crops.object import at_output, vote_neighbours, voted_rgba
    from dbb_capture.crops.object import rematte as second
    from dbb_capture.crops.sequences import follows_previous

    cap = capture_matte([oc.noise for oc in crops], counts, [oc.room_detail for oc in crops], cfg.sharp_min_detail)
    alphas = [second(oc, fill, cap, cfg) for oc in crops]
    linked = follows_previous(times)
    return [at_output(replace(oc, rgba=voted_rgba(oc, [alphas[j] for j in vote_neighbours(k, linked)]))).rgba
            for k, oc in enumerate(crops)]


def rematte(capture: Path, dataset: Path) -> tuple[Path, Path]:
    """Crop and matte every crop of ``dataset`` again (first pass; then both passes, as the crops
    stage does) with its own poses and background field; writes ``crops/`` of two copies of the
    dataset (``-first``, ``-two``) and returns them."""
    import shutil

    from dbb_capture.background.model import BackgroundModel
    from dbb_capture.capture.footage import open_footage
    from dbb_capture.crops.camera import crop_windows
    from dbb_capture.crops.matte import MatteConfig, sure_object_counts
    from dbb_capture.crops.object import at_output, matte_scale, object_crop

    intr = Intrinsics.load(dataset / "camera.json")
    doc = json.loads((dataset / "crops.json").read_text())
    center, radius, up = np.array(doc["object"]["center"]), doc["object"]["radius"], np.array(doc["up"])
    size, fill, cfg = doc["crop_size"], doc["crop_fill"], MatteConfig()
    model = BackgroundModel.load(dataset / "background" / "field.pt")
    frames = doc["frames"]
    images = {f.index: f.image for f in open_footage(capture / "video.mp4").read(sorted(fr["source_frame"] for fr in frames))}
    crops, counts = [], None
    scale = matte_scale(crop_windows([_estimated_c2w(dataset, fr) for fr in frames], intr, center, radius, up, fill),
                        size, cfg.supersample_between)
    for fr in frames:
        oc = object_crop(images[fr["source_frame"]], intr, _estimated_c2w(dataset, fr), center, radius, up, size, fill,
                         model.render, cfg, model.guessed, scale)
        crops.append(oc)
        if oc.guessed is not None and oc.guessed.any():
            c = sure_object_counts(oc.rgba, oc.guessed, cfg.colour_bins)
            counts = c if counts is None else counts + c
    voted = both_passes(crops, np.array([fr["time"] for fr in frames]), fill, cfg, counts)
    outs = []
    for tag in ("first", "two"):
        out = dataset.parent / f"{dataset.name}-{tag}"
        if out.exists():
            shutil.rmtree(out)
        shutil.copytree(dataset, out, ignore=shutil.ignore_patterns("images", "masks", "colmap"))
        outs.append(out)
    for fr, oc, two in zip(frames, crops, voted):
        for out, rgba in zip(outs, (at_output(oc).rgba, two)):
            cv2.imwrite(str(out / fr["file_path"]), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    return outs[0], outs[1]


def synth_scene(capture: Path):
    """The synthetic capture's scene rebuilt from its ``ground_truth/synth_config.json`` (the
    renderer's room, table, board and object, exactly as ``dbb-capture synth`` drew them)."""
    from dbb_capture.capture.board import BoardSpec
    from dbb_capture.synth.scene import SynthConfig, make_scene

    d = json.loads((capture / "ground_truth" / "synth_config.json").read_text())
    d = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
    cfg = SynthConfig(**{**d, "board": BoardSpec.from_json(d["board"])})
    return make_scene(cfg, np.random.default_rng(cfg.seed))


def budget_crops(capture: Path, cache: Path, size: int = 64, fill: float = 0.9, samples: int = 4) -> dict:
    """Per crop of a synthetic capture, through its *true* cameras (arrays (N, S, S[, 3]), cached
    in ``cache`` (npz)): the observed crop cut from the footage (``observed``), the room without
    the object rendered through the crop camera (``room``: a perfect background prediction), the
    scene rendered there without sensor noise or compression (``ideal``: perfect footage), the
    true coverage through the crop camera (``cover``, 0..1, ``samples`` x ``samples`` per pixel)
    and the capture's full-frame coverage cut through the crop warp (``warped``, 0..1: what
    ``score`` compares with); ``times`` (N,) s."""
    from dbb_capture.capture.footage import open_footage
    from dbb_capture.crops.camera import crop_camera
    from dbb_capture.synth.render import Renderer

    if cache.is_file():
        with np.load(cache) as z:
            return dict(z)
    intr = Intrinsics.load(capture / "ground_truth" / "camera.json")
    gt = json.loads((capture / "ground_truth" / "cameras.json").read_text())["video"]
    obj = json.loads((capture / "object.json").read_text())
    center, radius, up = np.array(obj["center"]), obj["radius"], np.array([0.0, 0.0, -1.0])
    scene = synth_scene(capture)
    empty = scene.without_object()
    out = {k: [] for k in ("observed", "room", "ideal", "cover", "warped", "times")}
    for f in open_footage(capture / "video.mp4").read(range(len(gt))):
        fr = gt[f.index]
        c2w = opencv_from_opengl(np.array(fr["transform_matrix"]))
        cam = crop_camera(c2w, intr, center, radius, up, size, fill)
        mask = cv2.imread(str(capture / "ground_truth" / "masks" / f"{f.index:05d}.png"), cv2.IMREAD_GRAYSCALE)
        r = Renderer(cam.intr, samples, adaptive=False)
        ideal, cover = r.render(scene, cam.c2w, fr["time"])
        room, _ = r.render(empty, cam.c2w, fr["time"])
        out["observed"].append(cut_crop(f.image, cam, intr, c2w)[0])
        out["room"].append(np.clip(np.round(room * 255), 0, 255).astype(np.uint8))
        out["ideal"].append(np.clip(np.round(ideal * 255), 0, 255).astype(np.uint8))
        out["cover"].append(cover.astype(np.float32))
        out["warped"].append(cut_crop(mask[..., None], cam, intr, c2w)[0].reshape(size, size).astype(np.float32) / 255)
        out["times"].append(fr["time"])
    arrays = {k: np.stack(v) for k, v in out.items()}
    np.savez_compressed(cache, **arrays)
    return arrays


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-crop IoU (N,) of boolean masks (N, H, W)."""
    return (a & b).sum((1, 2)) / np.maximum((a | b).sum((1, 2)), 1)


def outline_split(alpha: np.ndarray, truth: np.ndarray, px: float = 1.5) -> dict:
    """Where a matte (N, H, W) bool errs against ``truth`` (N, H, W) bool, as shares of the true
    object's area: missed / added within ``px`` of the true outline, and further away."""
    from scipy.ndimage import distance_transform_edt

    near = np.stack([np.minimum(distance_transform_edt(t), distance_transform_edt(~t)) <= px for t in truth])
    area = max(int(truth.sum()), 1)
    return {"missed_outline": float((truth & ~alpha & near).sum() / area),
            "added_outline": float((~truth & alpha & near).sum() / area),
            "missed_inside": float((truth & ~alpha & ~near).sum() / area),
            "added_outside": float((~truth & alpha & ~near).sum() / area)}


def budget(work: Path, captures: list[Path], fill: float = 0.9) -> list[dict]:
    """The matte's error budget on synthetic captures, through their true cameras:
    (a) the footage ceiling: the true coverage cut through the crop warp against the coverage
    through the crop camera (what resampling the footage alone costs at alpha > 0.5);
    (b0) the matte's ceiling: the matte (both passes) of a noise-free render through the crop
    camera against the room rendered there (perfect footage, perfect background);
    (b) the matte of the real footage's crop against the perfect background (what the footage's
    noise, compression and chroma cost the matte; the rest of the ``quality`` figure is the
    background field's)."""
    from dbb_capture.crops.matte import MatteConfig, matte_and_noise, sphere_disc
    from dbb_capture.crops.object import ObjectCrop

    cfg = MatteConfig()
    rows = []
    for cap in captures:
        z = budget_crops(cap, work / f"{cap.name}-budget.npz", fill=fill)
        size = z["observed"].shape[1]
        disc = sphere_disc(size, fill, cfg.disc_margin)
        cover, warped = z["cover"] > 0.5, z["warped"] > 0.5
        row = {"capture": cap.name, "crops": len(cover),
               "a_warp_vs_camera": float(np.median(iou(warped, cover))),
               "a_warp_vs_camera_p10": float(np.percentile(iou(warped, cover), 10))}
        for tag, images, truth in (("b0_ideal", z["ideal"], cover), ("b_footage", z["observed"], warped)):
            crops = []
            for obs, room in zip(images, z["room"]):
                rgba, noise, detail = matte_and_noise(obs, room, disc, cfg)
                crops.append(ObjectCrop(None, obs, room, rgba, False, None, None, noise, detail))
            two = np.stack(both_passes(crops, z["times"], fill, cfg))[..., 3] > 127
            first = np.stack([oc.rgba for oc in crops])[..., 3] > 127
            ious = iou(two, truth)
            row.update({f"{tag}_first": float(np.median(iou(first, truth))), tag: float(np.median(ious)),
                        f"{tag}_p10": float(np.percentile(ious, 10)),
                        **{f"{tag}_{k}": v for k, v in outline_split(two, truth).items()}})
            if tag == "b_footage":
                row["b_footage_vs_camera"] = float(np.median(iou(two, cover)))
        rows.append(row)
        print(json.dumps(row), flush=True)
    print("\n| capture | crops | (a) warp vs crop camera | (b0) matte, perfect footage + room | "
          "(b) matte, footage + perfect room | (b) first pass | (b) errors: missed / added at the outline, "
          "missed / added elsewhere (% of area) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['capture']} | {r['crops']} | {r['a_warp_vs_camera']:.3f} ({r['a_warp_vs_camera_p10']:.3f}) | "
              f"{r['b0_ideal']:.3f} ({r['b0_ideal_p10']:.3f}) | {r['b_footage']:.3f} ({r['b_footage_p10']:.3f}) | "
              f"{r['b_footage_first']:.3f} | {100 * r['b_footage_missed_outline']:.1f} / "
              f"{100 * r['b_footage_added_outline']:.1f} / {100 * r['b_footage_missed_inside']:.1f} / "
              f"{100 * r['b_footage_added_outside']:.1f} |")
    return rows


QUALITY_CROP = 64     # the matte's figures (docs/results.md) are at 64 px, whatever the footage


def run_preprocess(capture: Path, out: Path, *args: str) -> float:
    t = time.monotonic()
    cmd = [str(REPO / ".venv" / "bin" / "dbb-capture"), "preprocess", str(capture), "-o", str(out), "--overwrite",
           *args]
    subprocess.run(cmd, check=True)
    return time.monotonic() - t


def quality(work: Path, captures: list[Path], minutes: float, rescore: bool = False, again: bool = False,
            steps: int | None = None) -> None:
    """Preprocess each capture with and without its clean plate and score it (``rescore``: score
    the datasets already in ``work`` without running preprocess again; time shows as 0;
    ``again``: matte them again first, see :func:`rematte`)."""
    rows = []
    for cap in captures:
        for plate in (True, False):
            name = f"{cap.name}-{'plate' if plate else 'noplate'}"
            out = work / name
            budget = ["--background-steps", str(steps)] if steps else ["--background-minutes", str(minutes)]
            budget += ["--crop-size", str(QUALITY_CROP)]
            secs = 0.0 if rescore or again else run_preprocess(cap, out, *budget,
                                                               *([] if plate else ["--no-clean-plate"]))
            bg = json.loads((out / "dataset.json").read_text())["background"]
            if again:
                first, two = rematte(cap, out)
                s1 = score(cap, first)
                print(name, "first pass only:", json.dumps(s1), flush=True)
                rows.append((name + "-first pass", s1, secs, bg))
                out, name = two, name + "-two passes"
            s = score(cap, out)
            rows.append((name, s, secs, bg))
            print(name, json.dumps(s), f"{secs:.0f}s", bg, flush=True)
    print("\n| capture | background | crops | alpha IoU median (p10) | IoU, truth via true camera | "
          "centre error px@64 median / max | radius deviation max | up error median / max | preprocess time |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, s, secs, bg in rows:
        print(f"| {name.split('-', 1)[0]}{' (' + name.split('-', 2)[2] + ')' if name.count('-') > 1 else ''} | {bg['mode']}, {bg['steps']} steps | {s['crops']} | {s['iou_median']:.3f} "
              f"({s['iou_p10']:.3f}) | {s['iou_true_cam_median']:.3f} | "
              f"{s['centre_px64_median']:.3f} / {s['centre_px64_max']:.3f} | "
              f"{s['radius_dev_pct']:.2f}% | {s['up_deg_median']:.3f} / {s['up_deg_max']:.3f} deg | {secs:.0f} s |")


def speed(work: Path, minutes: float) -> None:
    from dbb_capture.background.model import BackgroundModel
    from dbb_capture.capture.board import BoardSpec
    from dbb_capture.capture.footage import open_footage
    from dbb_capture.crops.matte import capture_matte
    from dbb_capture.crops.object import at_output, object_crop, rematte, voted_rgba
    from dbb_capture.geometry.viewpoint import up_from_cameras
    from dbb_capture.poses.detect import DetectorConfig, detect_frames
    from dbb_capture.poses.path import fuse_with_path
    from dbb_capture.poses.solve import pose_frames

    cap = work / "hd"
    if not (cap / "video.mp4").is_file():
        subprocess.run([str(REPO / ".venv" / "bin" / "dbb-capture"), "synth", str(cap), "--kind", "static",
                        "--seconds", "3", "--background-seconds", "15", "--fps", "10", "--resolution", "1920x1440",
                        "--seed", "31", "--overwrite"], check=True)
    ds = work / "hd-dataset"
    t_bg = run_preprocess(cap, ds, "--stop-after", "background", "--background-minutes", str(minutes))
    rep = json.loads((ds / "background" / "report.json").read_text())
    model = BackgroundModel.load(ds / "background" / "field.pt")
    intr = Intrinsics.load(ds / "camera.json")
    board = BoardSpec.load(cap / "board.json")
    obj = json.loads((cap / "object.json").read_text())
    frames = list(open_footage(cap / "video.mp4").read(range(30)))
    timings = {"pose": 0.0, "crop+render+matte": 0.0, "second pass": 0.0}
    n = 0
    c2ws, dets, poses = [], [], []
    t_all = time.monotonic()
    crops, noises, details = [], [], []
    for f in frames:
        t = time.monotonic()
        d = detect_frames([f], board, DetectorConfig())[0]
        p = pose_frames([d], board, intr)[0]
        timings["pose"] += time.monotonic() - t
        dets.append(d)
        poses.append(p)
        if p.c2w is None:
            continue
        c2ws.append(p.c2w)
        up = up_from_cameras(np.stack(c2ws))
        t = time.monotonic()
        oc = object_crop(f.image, intr, p.c2w, np.array(obj["center"]), obj["radius"], up, 64, 0.9, model.render,
                         guessed=model.guessed)
        noises.append(oc.noise)
        details.append(oc.room_detail)
        timings["crop+render+matte"] += time.monotonic() - t
        crops.append(oc)
        n += 1
    # The poses' fusion with the camera path is a pass over all frames (the crops above use the
    # per-frame poses: the same work per frame, and the timing is what is measured here).
    t = time.monotonic()
    fuse_with_path(dets, poses, board, intr)
    timings["path fusion"] = time.monotonic() - t
    # The matte's second pass (capture statistics, matte again, temporal median of 3), per frame.
    t = time.monotonic()
    capture = capture_matte(noises, None, details)
    alphas = [rematte(oc, 0.9, capture) for oc in crops]
    for k, oc in enumerate(crops):
        at_output(replace(oc, rgba=voted_rgba(oc, alphas[max(0, k - 1):k + 2])))
    timings["second pass"] = time.monotonic() - t
    total = time.monotonic() - t_all
    print(f"background stage (pose {rep['clean_plate']['frames']}-frame clean plate, cut crops, plane sweep, "
          f"train {minutes} min): {t_bg:.0f} s; {rep['steps']} steps, training PSNR {rep['train_psnr_db']} dB")
    print(f"per frame at 1920x1440, {n} frames, 1 process: pose {timings['pose'] / len(frames) * 1000:.0f} ms, "
          f"fusion with the camera path {timings['path fusion'] / max(n, 1) * 1000:.1f} ms, "
          f"crop+render+matte {timings['crop+render+matte'] / max(n, 1) * 1000:.0f} ms, "
          f"second matte pass {timings['second pass'] / max(n, 1) * 1000:.1f} ms; "
          f"{len(frames) / total:.1f} frames/s (2 processes: about {2 * len(frames) / total:.1f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("what", choices=["quality", "speed", "budget"])
    ap.add_argument("--work", type=Path, default=Path("out/bench/pre"))
    ap.add_argument("--minutes", type=float, default=2.0, help="background field training budget")
    ap.add_argument("--steps", type=int, default=None,
                    help="quality: train the background field for this many steps instead (a run whose result "
                         "does not depend on the machine's load)")
    ap.add_argument("--rescore", action="store_true", help="quality: score the datasets in --work again")
    ap.add_argument("--rematte", action="store_true",
                    help="quality: crop and matte the datasets in --work again (their fields kept), then score")
    ap.add_argument("--captures", type=Path, nargs="*",
                    default=[REPO / "sample_data" / "static", REPO / "sample_data" / "dynamic"])
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    if a.what == "quality":
        quality(a.work, a.captures, a.minutes, a.rescore, a.rematte, a.steps)
    elif a.what == "budget":
        budget(a.work, a.captures)
    else:
        speed(a.work, a.minutes)


if __name__ == "__main__":
    sys.exit(main())
