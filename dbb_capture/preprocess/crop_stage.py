"""The crops stage: per posed frame a crop camera, the predicted room, a two-pass matte and a
straight RGBA crop; ``crops.json``, full-frame masks and ``dataset.json``.

The passes run over contiguous segments of the footage, in spawned worker processes when there
are enough frames (:func:`..core.parallel.map_spawned`)."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..background.model import BackgroundModel
from ..background.rays import room_rays
from ..background.train import refine_on_room
from ..capture.footage import FootageSource
from ..core.images import write_image
from ..core.outputs import write_json
from ..core.progress import progress
from ..crops.matte import CaptureMatte, MatteConfig, capture_matte, sure_object_counts
from ..crops.object import (
    ObjectCrop,
    alpha_in_frame,
    at_output,
    object_crop,
    rematte,
    vote_neighbours,
    voted_rgba,
)
from ..crops.sequences import follows_previous, sequence_windows, split_by_time
from ..datasets.records import Frame
from ..datasets.transforms import write_crops
from ..geometry.cameras import Intrinsics
from .background_stage import BackgroundOutput, ObjectSphere
from .inputs import StageContext
from .pose_stage import POINT_CLOUD, write_frames
from .report import contact_sheet, dataset_stats, sheet_frame, sheet_tiles


@dataclass(frozen=True)
class CropsOutput:
    """The crops stage's record: the crops dataset file and its records."""

    crops_json: Path
    frames: tuple[Frame, ...]        # the crops, each its own camera
    stats: dict


@dataclass(frozen=True)
class _CropSegment:
    """One worker's share of the crops stage's first pass: contiguous frames and everything to
    crop, predict and matte them."""

    source: FootageSource
    c2w: dict                    # frame index -> (4, 4) OpenCV c2w
    intr: Intrinsics             # of the footage (distortion included)
    sphere: ObjectSphere
    size: int
    fill: float
    matte: MatteConfig
    scale: int                   # the matte runs at this many times ``size`` (:func:`~.crops.matte_scale`)
    model: Path                  # background/field.pt
    scratch: Path                # where the first pass leaves each crop's arrays for the second
    sheet_at: frozenset


@dataclass(frozen=True)
class _FirstMatte:
    """A crop after the first pass (its arrays in the scratch folder)."""

    index: int
    name: str
    cam: Any
    touches_border: bool
    noise: float                 # the matte's noise level in this crop
    room_detail: float = float("nan")  # share of the room's detail the prediction keeps (nan: not measured)
    scale: int = 1               # the scratch arrays (and ``cam``) are at this many times the output size


@dataclass(frozen=True)
class _FirstPass:
    crops: list[_FirstMatte]
    object_counts: np.ndarray | None   # (bins,)*3 sure object colours where a prediction was a guess


@dataclass(frozen=True)
class _MatteSegment:
    """One worker's share of the second pass: its crops, their temporal neighbours just outside
    the segment (None: not the next frame) and the capture's statistics."""

    crops: tuple[_FirstMatte, ...]
    before: _FirstMatte | None
    after: _FirstMatte | None
    follows: frozenset           # frame indices that directly follow the previous crop in time (no gap)
    c2w: dict
    frame_intr: Intrinsics       # of the undistorted frames (masks are drawn there)
    fill: float
    matte: MatteConfig
    capture: CaptureMatte
    scratch: Path
    out: Path
    sheet_at: frozenset


@dataclass(frozen=True)
class _CropResult:
    index: int
    cam: Any
    touches_border: bool
    coverage: float
    sheet_row: np.ndarray | None


_MODELS: dict = {}  # background model per path, loaded once per process


def _crop_segment(seg: _CropSegment, tick: Callable[[int], None] | None = None) -> _FirstPass:
    """First pass over one segment (in this or a spawned process): crop, predict, matte; keeps
    each crop's arrays for the second pass and what the capture's statistics need."""
    from ..core.parallel import report

    tick = tick or report
    if seg.model not in _MODELS:
        _MODELS[seg.model] = BackgroundModel.load(seg.model)
    model = _MODELS[seg.model]
    sp, out, counts = seg.sphere, [], None
    for f in seg.source.read(sorted(seg.c2w)):
        c2w = seg.c2w[f.index]
        oc = object_crop(f.image, seg.intr, c2w, sp.center, sp.radius, sp.up, seg.size, seg.fill,
                         model.render, seg.matte, model.guessed, seg.scale)
        if oc.guessed is not None and oc.guessed.any():
            c = sure_object_counts(oc.rgba, oc.guessed, seg.matte.colour_bins)
            counts = c if counts is None else counts + c
        extra = {}
        if f.index in seg.sheet_at:
            extra["sheet_frame"] = sheet_frame(f.image, oc.cam, seg.intr, c2w, sp.center)
        np.savez(seg.scratch / f"{f.name}.npz", observed=oc.observed, predicted=oc.predicted, alpha=oc.rgba[..., 3],
                 guessed=oc.guessed if oc.guessed is not None else np.zeros(0, bool),
                 inside=oc.inside if oc.inside is not None else np.zeros(0, np.uint8), **extra)
        out.append(_FirstMatte(f.index, f.name, oc.cam, oc.touches_border, oc.noise, oc.room_detail, oc.scale))
        tick(1)
    return _FirstPass(out, counts)


def _load_crop(scratch: Path, fm: _FirstMatte, first_alpha: bool = False) -> tuple[ObjectCrop, np.ndarray | None]:
    """A first-pass crop back from the scratch folder, and its contact-sheet frame. Its RGBA is
    empty, or with ``first_alpha`` the observed colour under the first pass's alpha."""
    with np.load(scratch / f"{fm.name}.npz") as z:
        g, inside = z["guessed"], z["inside"]
        rgba = np.concatenate([z["observed"], z["alpha"][..., None]], -1) if first_alpha else np.zeros(0, np.uint8)
        oc = ObjectCrop(fm.cam, z["observed"], z["predicted"], rgba, fm.touches_border,
                        g if g.size else None, inside if inside.size else None, scale=fm.scale)
        return oc, (z["sheet_frame"] if "sheet_frame" in z else None)


def _matte_segment(seg: _MatteSegment, tick: Callable[[int], None] | None = None) -> list[_CropResult]:
    """Second pass over one segment: matte again with the capture's statistics, take the
    temporal median with the neighbouring frames' alphas, write the crops and masks."""
    from ..core.parallel import report

    tick = tick or report
    chain = [c for c in (seg.before, *seg.crops, seg.after) if c is not None]
    loaded: dict = {}                                      # frame index -> (crop, sheet frame, second alpha)

    def load(fm: _FirstMatte) -> tuple:
        if fm.index not in loaded:
            oc, sheet_frame = _load_crop(seg.scratch, fm)
            loaded[fm.index] = (oc, sheet_frame, rematte(oc, seg.fill, seg.capture, seg.matte))
        return loaded[fm.index]

    mine = {c.index for c in seg.crops}
    for sub in ("crops_observed", "crops_background"):
        (seg.out / sub).mkdir(exist_ok=True)
    linked = np.array([c.index in seg.follows for c in chain])
    out, prev = [], None
    for k, fm in enumerate(chain):
        if fm.index not in mine:
            continue
        nb = [chain[j] for j in vote_neighbours(k, linked)]
        oc, sheet_frame, _ = load(fm)
        oc = at_output(replace(oc, rgba=voted_rgba(oc, [load(c)[2] for c in nb])))
        for i in [i for i in loaded if i < chain[max(0, k - 1)].index]:
            del loaded[i]                                  # keep the sliding window small
        write_image(seg.out / f"crops/{fm.name}.png", cv2.cvtColor(oc.rgba, cv2.COLOR_RGBA2BGRA))
        if not oc.touches_border:       # past the border the observed crop is padding, not the room
            write_image(seg.out / f"crops_observed/{fm.name}.png", cv2.cvtColor(oc.observed, cv2.COLOR_RGB2BGR))
            write_image(seg.out / f"crops_background/{fm.name}.png", cv2.cvtColor(oc.predicted, cv2.COLOR_RGB2BGR))
        # Full-frame masks are binary at half opacity (nerfstudio samples where a mask is above 0,
        # so soft edges would count as object); the crops keep the soft alpha.
        alpha = alpha_in_frame(oc.rgba[..., 3], oc.cam, seg.frame_intr, seg.c2w[fm.index])
        write_image(seg.out / f"masks/{fm.name}.png", np.where(alpha >= 128, 255, 0).astype(np.uint8))
        row = sheet_tiles(sheet_frame, oc, prev) if sheet_frame is not None else None
        out.append(_CropResult(fm.index, oc.cam, oc.touches_border, float(oc.rgba[..., 3].mean()) / 255.0, row))
        prev = oc.rgba
        tick(1)
    return out


def _refine_background(ctx: StageContext, bg: BackgroundOutput, crops: list[_FirstMatte], scratch: Path,
                       prog) -> BackgroundOutput:
    """The object-video field trained again on the first mattes' room rays
    (:func:`~dbb_capture.background.field.refine_on_room`); saved over background/field.pt."""
    grow = bg.model.cfg.refine_grow_px

    def rays():
        for fm in crops:
            # at the output size: the rays and the margin are the same whatever the matte's scale
            oc = at_output(_load_crop(scratch, fm, first_alpha=True)[0])
            yield room_rays(oc.cam, oc.observed, oc.rgba[..., 3], oc.inside, grow)

    task = prog.add_task("train background again on the mattes' room", total=100, info="")
    model = refine_on_room(bg.model, rays(), lambda log, frac: prog.update(
        task, completed=100 * frac, info=f"psnr {log.psnr:.1f} dB, step {log.steps}"))
    if model.refine is None:
        return bg
    model.save(ctx.out / "background" / "field.pt")
    report = {**bg.report, "refined_on_room": {"steps": model.refine.steps, "seconds": round(model.refine.seconds, 1),
                                               "train_psnr_db": round(model.refine.psnr, 2)}}
    write_json(ctx.out / "background" / "report.json", report)
    ctx.notes.append(f"background trained again on the first mattes' room: {model.refine.steps} steps, "
                     f"training PSNR {model.refine.psnr:.1f} dB")
    return replace(bg, model=model, report=report)


def crops_stage(ctx: StageContext, bg: BackgroundOutput) -> CropsOutput:
    """Every posed frame -> RGBA crop; writes crops/, masks/, crops.json, dataset.json,
    contact_sheet.png, and crops_observed/ and crops_background/ (the observed crop and the room
    predicted there, RGB: what the matte was cut from; referenced per frame in crops.json, except
    for crops past the frame's border).

    Two passes (:mod:`.matte`): the first crops, predicts and mattes every frame and learns the
    capture's statistics; the second mattes again with them and votes over neighbouring frames.
    With ``workers`` > 1 and 40+ frames, contiguous segments go to spawned processes.
    """
    from ..core.parallel import map_spawned, split

    inp, cfg, out = ctx.inputs, ctx.cfg, ctx.out
    poses, sphere = bg.poses, bg.sphere
    posed = poses.run.posed
    splits = split_by_time(np.array([p.time for p in posed]), cfg.test_fraction)
    (out / "crops").mkdir()
    (out / "masks").mkdir()
    scratch = out / "matte_scratch"
    scratch.mkdir()
    indices = [p.index for p in posed]
    sheet_at = frozenset(indices[i] for i in np.linspace(0, len(posed) - 1, min(8, len(posed))).round().astype(int))
    c2w = {p.index: p.c2w for p in posed}
    workers = max(1, min(cfg.workers, len(indices) // 20))
    parts = split(indices, workers)
    windows, scale, size = bg.geometry.windows, bg.geometry.scale, bg.geometry.crop_size
    if scale > 1:
        ctx.notes.append(f"crops matted at {scale}x ({scale * size} px) and averaged down: the crop window "
                         f"spans {np.median(windows) / size:.1f} source pixels per crop pixel (median)")

    def run(fn, tasks, task):
        if workers > 1:
            return map_spawned(fn, tasks, workers, lambda n: prog.advance(task, n))
        return [fn(t, lambda n: prog.advance(task, n)) for t in tasks]

    def first_pass(model: BackgroundModel) -> list[_FirstPass]:
        task = prog.add_task("crop and matte", total=len(posed), info="")
        _MODELS.pop(out / "background" / "field.pt", None)
        if workers == 1:
            _MODELS[out / "background" / "field.pt"] = model
        return run(_crop_segment, [_CropSegment(inp.footage, {i: c2w[i] for i in idx}, poses.run.intrinsics, sphere,
                                                size, cfg.crop_fill, cfg.matte, scale, out / "background" / "field.pt",
                                                scratch, sheet_at) for idx in parts], task)

    with progress(transient=True) as prog:
        first = first_pass(bg.model)
        crops = [c for part in first for c in part.crops]
        if bg.model.mode == "object video" and cfg.background.refine_share > 0:
            # No clean plate: the field learns the room again where the first mattes see it
            # through the object's sphere, then every crop is matted with it.
            bg = _refine_background(ctx, bg, crops, scratch, prog)
            first = first_pass(bg.model)
            crops = [c for part in first for c in part.crops]
        counts = [p.object_counts for p in first if p.object_counts is not None]
        capture = capture_matte([c.noise for c in crops], sum(counts) if counts else None,
                                [c.room_detail for c in crops], cfg.matte.sharp_min_detail)
        task = prog.add_task("second matte", total=len(posed), info="")
        linked = follows_previous(np.array([p.time for p in posed]))
        follows = frozenset(i for i, f in zip(indices, linked) if f)
        segs, at = [], 0
        for idx in parts:
            mine = tuple(crops[at:at + len(idx)])
            before = crops[at - 1] if at > 0 else None
            after = crops[at + len(idx)] if at + len(idx) < len(crops) else None
            segs.append(_MatteSegment(mine, before, after, follows, c2w, poses.intrinsics, cfg.crop_fill, cfg.matte, capture,
                                      scratch, out, sheet_at))
            at += len(idx)
        parts2 = run(_matte_segment, segs, task)
    shutil.rmtree(scratch)
    results = [r for part in parts2 for r in part]
    frames = [Frame(p.name, out / f"crops/{p.name}.png", r.cam.c2w, r.cam.intr, str(sp), time=p.time,
                    observed_path=None if r.touches_border else out / f"crops_observed/{p.name}.png",
                    background_path=None if r.touches_border else out / f"crops_background/{p.name}.png",
                    source_frame=p.index, viewpoint=r.cam.viewpoint, touches_border=r.touches_border)
              for p, sp, r in zip(posed, splits, results)]
    coverage = [r.coverage for r in results]
    sheet_rows = [r.sheet_row for r in results if r.sheet_row is not None]
    sheet_names = [p.name for p, r in zip(posed, results) if r.sheet_row is not None]
    windows = sequence_windows(np.array([f.time for f in frames]), splits, cfg.sequence_length)
    write_crops(out / "crops.json", frames, sphere.center, sphere.radius, sphere.up, size, cfg.crop_fill,
                cfg.sequence_length, windows,
                {"ply_file_path": POINT_CLOUD,
                 "note": "crop cameras: OpenGL camera-to-world, ChArUco board frame, metres; straight RGBA crops"})
    # The full frames get their masks (single channel, black = not the object).
    write_frames(out / "transforms.json", [replace(im, mask_path=out / "masks" / f"{im.name}.png")
                                           for im in poses.images], poses.up)
    if sheet_rows:
        write_image(out / "contact_sheet.png", cv2.cvtColor(contact_sheet(sheet_rows, sheet_names), cv2.COLOR_RGB2BGR))
    touched = [f.name for f in frames if f.touches_border]
    if touched:
        ctx.notes.append(f"{len(touched)} crops reach past the frame's border (padded transparent, flagged "
                         f"touches_border in crops.json): {', '.join(touched[:6])}"
                         f"{' ...' if len(touched) > 6 else ''}")
    stats = dataset_stats(frames, windows, cfg, sphere, poses, bg, coverage)
    write_json(out / "dataset.json", stats)
    return CropsOutput(out / "crops.json", tuple(frames), stats)
