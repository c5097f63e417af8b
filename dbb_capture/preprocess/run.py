"""``dbb-capture preprocess``: a capture folder -> a posed dataset, as a list of stages.

Each stage is a function ``(ctx, previous record) -> record`` writing its files into the
dataset folder being built, so a later stage can also start from those files alone. The
whole dataset is written aside and renamed into place at the end (``atomic_dir``).

Stages: ``poses`` (footage -> undistorted frames, ``transforms.json``, COLMAP model, pose
report), ``background`` (a radiance field of the room, from the clean plate or from the object
video with the object's sphere left out; :mod:`.background`), ``crops`` (per frame: crop
camera, predicted background, matte, straight RGBA crop; ``crops.json``, full-frame masks,
``dataset.json`` statistics and a contact sheet).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..background.field import (
    BackgroundConfig,
    BackgroundModel,
    PosedView,
    parallax_coverage,
    refine_on_room,
    room_rays,
    train_background,
    training_size,
)
from ..capture.board import BoardSpec
from ..geometry.cameras import Intrinsics, project_points
from ..crops.camera import (
    CropRecord,
    ObjectCrop,
    alpha_in_frame,
    at_output,
    crop_windows,
    crops_json,
    follows_previous,
    matte_scale,
    object_crop,
    on_checker,
    rematte,
    split_by_time,
    temporal_difference,
    vote_neighbours,
    voted_rgba,
)
from ..geometry.viewpoint import up_from_cameras
from ..core.errors import DbbError, InputError
from ..poses.export import (
    PosedImage,
    Undistorter,
    plot_camera_path,
    pose_report,
    write_colmap,
    write_transforms,
)
from ..capture.footage import FootageSource, R3dSource, capture_footage, open_footage
from ..crops.matte import CaptureMatte, MatteConfig, capture_matte, matte, sure_object_counts
from ..core.outputs import atomic_dir, read_json, write_json
from ..poses.detect import DetectorConfig
from ..poses.solve import PoseConfig
from ..poses.run import PoseRun, estimate_poses
from ..core.progress import progress


# --------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class CaptureInputs:
    """Where a capture's parts are. ``camera`` is None when intrinsics must be calibrated."""

    root: Path
    footage: FootageSource
    board: BoardSpec | None          # None only in fixed-camera mode (no board needed)
    camera: Intrinsics | None
    camera_source: str
    object_json: Path | None
    background: Path | None


def resolve_capture(capture: Path, board: Path | None = None, camera: Path | None = None,
                    footage: Path | None = None, object_json: Path | None = None,
                    background: Path | None = None, need_board: bool = True) -> CaptureInputs:
    """Find the parts of a capture folder (flags override the files inside it)."""
    capture = Path(capture)
    if not capture.is_dir():
        raise InputError(f"capture folder not found: {capture}")
    src = open_footage(footage) if footage else capture_footage(capture)
    src.info  # probe now: unreadable footage fails before any work starts
    board_spec = None
    if need_board or board is not None or (capture / "board.json").is_file():
        board_spec = BoardSpec.load(board or capture / "board.json")
    cam_path = camera or (capture / "camera.json" if (capture / "camera.json").is_file() else None)
    intr, cam_src = None, "calibrated from the footage"
    if cam_path is not None:
        intr, cam_src = Intrinsics.load(cam_path), str(cam_path)
    elif isinstance(src, R3dSource):
        intr, cam_src = src.intrinsics(), "Record3D metadata"
    obj = object_json or (capture / "object.json" if (capture / "object.json").is_file() else None)
    if background is None:
        for cand in ("background.mp4", "background.mov", "background"):
            if (capture / cand).exists():
                background = capture / cand
                break
    return CaptureInputs(capture, src, board_spec, intr, cam_src, obj, background)


# --------------------------------------------------------------------------- stages
@dataclass(frozen=True)
class PreprocessConfig:
    """Options of a run. ``fps``: resample the footage (None: every frame)."""

    fps: float | None = None
    blur_ratio: float = 0.4
    refine: bool = False
    workers: int = 1
    stop_after: str | None = None
    detector: DetectorConfig = DetectorConfig()
    gates: PoseConfig = PoseConfig()
    crop_size: int = 64
    crop_fill: float = 0.9
    test_fraction: float = 0.2
    sequence_length: int = 11
    use_clean_plate: bool = True          # False: learn the room from the object video even if a plate exists
    fixed_window: tuple[int, int, int] | None = None   # fixed camera: crop window (x, y, side) in pixels
    fixed_matte: bool = True              # fixed camera: matte against the background (False: opaque crops)
    background: BackgroundConfig = BackgroundConfig()
    matte: MatteConfig = MatteConfig()

    def validate(self) -> None:
        if not 16 <= self.crop_size <= 1024:
            raise DbbError(f"--crop-size {self.crop_size}: expected 16..1024 pixels")
        if not 0.2 <= self.crop_fill <= 1.0:
            raise DbbError(f"--crop-fill {self.crop_fill}: expected 0.2..1")
        if not 0.0 <= self.test_fraction < 1.0:
            raise DbbError(f"--test-fraction {self.test_fraction}: expected 0 <= f < 1")
        if self.sequence_length < 2:
            raise DbbError("--sequence-length must be at least 2 (1 context + 1 predicted frame)")
        self.background.validate()


@dataclass
class StageContext:
    """What every stage sees: the inputs, the options and the dataset folder being written."""

    inputs: CaptureInputs
    cfg: PreprocessConfig
    out: Path
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class PosesOutput:
    """The poses stage's record: the dataset's (undistorted) camera and its posed images."""

    transforms: Path
    intrinsics: Intrinsics           # of the undistorted frames
    images: tuple[PosedImage, ...]
    run: PoseRun


@dataclass(frozen=True)
class Stage:
    name: str
    run: Callable[[StageContext, Any], Any]


def poses_stage(ctx: StageContext, _previous: Any = None) -> PosesOutput:
    """Footage -> poses; writes images/, transforms.json, camera.json, colmap/sparse/0, poses/."""
    inp, cfg, out = ctx.inputs, ctx.cfg, ctx.out
    with progress(transient=True) as prog:
        task = prog.add_task("detect board", total=None, info="")
        run = estimate_poses(
            inp.footage, inp.board, inp.camera, fps=cfg.fps, blur_ratio=cfg.blur_ratio,
            refine=cfg.refine, workers=cfg.workers, det_cfg=cfg.detector, pose_cfg=cfg.gates,
            tick=lambda n: prog.advance(task, n), total=lambda n: prog.update(task, total=n),
            intr_source=inp.camera_source,
            device_c2w=inp.footage.arkit_c2w_opencv() if isinstance(inp.footage, R3dSource) else None)
        posed = run.posed
        undistort = Undistorter(run.intrinsics)
        (out / "images").mkdir()
        task = prog.add_task("write undistorted frames", total=len(posed), info="")
        images = []
        by_index = {p.index: p for p in posed}
        for f in inp.footage.read(sorted(by_index)):
            p = by_index[f.index]
            rel = f"images/{f.name}.png"
            img = undistort(f.image)
            bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
            if not cv2.imwrite(str(out / rel), bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                raise DbbError(f"cannot write {out / rel}")
            images.append(PosedImage(rel, p.c2w, p.time))
            prog.advance(task)
    intr = undistort.target
    # "Up" is the board normal on the cameras' side, read from the poses, never assumed.
    side = np.sign(np.median([im.c2w[2, 3] for im in images])) or -1.0
    up = [0.0, 0.0, float(side)]
    write_transforms(out / "transforms.json", intr, images,
                     {"up": up, "note": "OpenGL camera-to-world, ChArUco board frame, metres; "
                                        "frames undistorted"})
    cam = run.intrinsics.to_json()
    if run.calibration is not None:
        cam["rms"] = round(run.calibration.rms, 4)
    write_json(out / "camera.json", cam)
    write_colmap(out / "colmap" / "sparse" / "0", intr, images)
    write_json(out / "poses" / "report.json", pose_report(run, inp.board))
    plot_camera_path(run, inp.board, out / "poses" / "camera_path.png")
    write_json(out / "board.json", inp.board.to_json())
    if inp.object_json is not None:
        shutil.copyfile(inp.object_json, out / "object.json")
    else:
        ctx.notes.append("no object.json in the capture: later stages must estimate the object's sphere")
    skipped = [p for p in run.frames if not p.posed]
    if skipped:
        why: dict[str, list[str]] = {}
        for p in skipped:
            why.setdefault(p.status, []).append(p.name)
        ctx.notes.append(f"{len(skipped)} of {len(run.frames)} frames skipped: " + "; ".join(
            f"{k} ({len(v)}: {', '.join(v[:6])}{' ...' if len(v) > 6 else ''})" for k, v in sorted(why.items())))
    return PosesOutput(out / "transforms.json", intr, tuple(images), run)


@dataclass(frozen=True)
class ObjectSphere:
    """The sphere that holds the object (board frame, metres) and the scene's up (3,)."""

    center: np.ndarray
    radius: float
    up: np.ndarray
    source: str                      # "object.json" or how it was estimated


@dataclass(frozen=True)
class BackgroundOutput:
    """The background stage's record: the trained room and what it was made from."""

    poses: PosesOutput
    sphere: ObjectSphere
    model: BackgroundModel
    report: dict
    windows: np.ndarray          # (N,) crop window of each posed frame, source pixels (:func:`matte_geometry`)
    scale: int                   # the crops are matted at this many times their size


def object_sphere(ctx: StageContext, poses: PosesOutput) -> ObjectSphere:
    """Read (or estimate, saying so) the object's sphere; check that the views see it."""
    c2ws = np.stack([im.c2w for im in poses.images])
    up = up_from_cameras(c2ws)
    if (ctx.out / "object.json").is_file():
        obj = read_json(ctx.out / "object.json", "object sphere")
        try:
            center, radius = np.asarray(obj["center"], float).reshape(3), float(obj["radius"])
        except (KeyError, TypeError, ValueError):
            raise InputError('object.json must be {"center": [x, y, z], "radius": r} (board frame, metres)') from None
        if radius <= 0:
            raise InputError(f"object.json: radius must be positive (got {radius})")
        source = "object.json"
    else:
        from ..datasets.records import Frame as DsFrame
        from ..datasets.records import estimate_volume

        vol = estimate_volume([DsFrame(im.file_path, ctx.out / im.file_path, im.c2w, poses.intrinsics)
                               for im in poses.images])
        center, radius = np.asarray(vol.center), vol.radius
        source = "estimated from where the cameras look (no object.json)"
        ctx.notes.append(f"object sphere {source}: centre {np.round(center, 3).tolist()}, radius {radius:.3f} m")
        write_json(ctx.out / "object.json", {"center": center.round(6).tolist(), "radius": round(radius, 6),
                                             "estimated": True})
    intr = poses.intrinsics
    uv = np.stack([project_points(center[None], c, intr)[0] for c in c2ws])
    depth = np.einsum("nj,nj->n", center - c2ws[:, :3, 3], c2ws[:, :3, 2])
    inside = (depth > radius) & (uv[:, 0] >= 0) & (uv[:, 0] < intr.width) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height)
    if inside.mean() < 0.5:
        raise InputError(f"the object's sphere ({source}: centre {np.round(center, 3).tolist()} m) is outside "
                         f"the view in {int((~inside).sum())} of {len(inside)} posed frames: check its centre "
                         f"(board frame, metres, origin at the board's top-left corner)")
    if not inside.all():
        ctx.notes.append(f"object centre outside the frame in {int((~inside).sum())} posed frames")
    return ObjectSphere(center, radius, up, source)


def matte_geometry(cfg: PreprocessConfig, poses: PosesOutput, sphere: ObjectSphere) -> tuple[np.ndarray, int]:
    """The crop windows (N,) of the posed frames in source pixels and the scale the crops are
    matted at (:func:`~.crops.matte_scale`)."""
    windows = crop_windows([p.c2w for p in poses.run.posed], poses.run.intrinsics, sphere.center, sphere.radius,
                           sphere.up, cfg.crop_size, cfg.crop_fill)
    return windows, matte_scale(windows, cfg.crop_size, cfg.matte.supersample_between)


def _subsample(items: list, n: int) -> list:
    if len(items) <= n:
        return items
    return [items[i] for i in np.unique(np.linspace(0, len(items) - 1, n).round().astype(int))]


def _posed_views(src: FootageSource, intr: Intrinsics, posed: list) -> Iterator[PosedView]:
    """The frames of ``posed`` (posed frame records) read from ``src`` as a stream of views."""
    by_index = {p.index: p for p in posed}
    if by_index:
        for f in src.read(sorted(by_index)):
            yield PosedView(f.image, intr, by_index[f.index].c2w)


def background_stage(ctx: StageContext, poses: PosesOutput) -> BackgroundOutput:
    """Train the room's field; writes background/field.pt and background/report.json."""
    inp, cfg = ctx.inputs, ctx.cfg
    sphere = object_sphere(ctx, poses)
    intr = poses.run.intrinsics                      # of the footage as filmed (distortion included)
    plate = inp.background if cfg.use_clean_plate else None
    folder = ctx.out / "background"
    folder.mkdir()
    windows, scale = matte_geometry(cfg, poses, sphere)
    bg_cfg = replace(cfg.background, train_size=training_size(cfg.background, cfg.crop_size * scale, cfg.crop_fill,
                                                              float(np.median(windows)) if len(windows) else 0.0))
    report: dict = {}
    with progress(transient=True) as prog:
        if plate is not None:
            src = open_footage(plate)
            if (src.info.width, src.info.height) != (intr.width, intr.height):
                raise InputError(f"the clean plate {plate.name} is {src.info.width}x{src.info.height} but the video "
                                 f"is {intr.width}x{intr.height}: film both with the same camera settings")
            task = prog.add_task("pose clean plate", total=None, info="")
            prun = estimate_poses(src, inp.board, intr, fps=cfg.fps, blur_ratio=cfg.blur_ratio,
                                  workers=cfg.workers, det_cfg=cfg.detector, pose_cfg=cfg.gates,
                                  tick=lambda n: prog.advance(task, n), total=lambda n: prog.update(task, total=n),
                                  intr_source=poses.run.intrinsics_source)
            posed = _subsample(prun.posed, bg_cfg.max_frames)
            report["clean_plate"] = {"file": plate.name, "frames": len(prun.frames), "posed": len(prun.posed)}
        else:
            src = inp.footage
            posed = _subsample(poses.run.posed, bg_cfg.max_frames)
            par = parallax_coverage(np.stack([p.c2w for p in posed]), sphere.center, sphere.radius, sphere.up)
            report["parallax_coverage"] = round(par, 3)
            if par < 0.5:
                raise InputError(f"no clean plate, and too little parallax to see behind the object (other views "
                                 f"see {100 * par:.0f}% of the table it hides, need 50%): film a clean plate "
                                 f"(background.mp4) or move around the object more")
        # With a plate, the video's rays past the object's sphere join it (BackgroundConfig.video_room).
        video = _subsample(poses.run.posed, bg_cfg.max_frames) if plate is not None and bg_cfg.video_room else []
        task = prog.add_task("cut training crops", total=len(posed) + len(video), info="")
        views, room_views = _posed_views(src, intr, posed), _posed_views(inp.footage, intr, video)
        train_task = prog.add_task("train background field", total=100, info="")

        def on_step(log, frac):
            prog.update(train_task, completed=100 * frac, info=f"psnr {log.psnr:.1f} dB, step {log.steps}")

        model = train_background(views, len(posed), sphere.center, sphere.radius, sphere.up,
                                 clean_plate=plate is not None, cfg=bg_cfg, on_step=on_step,
                                 tick=lambda: prog.advance(task), room_views=room_views)
    model.save(folder / "field.pt")
    mode = "clean plate" if plate is not None else "object video (rays through the object's sphere left out)"
    if video:
        report["video_room_frames"] = len(video)
    report.update({"mode": mode, "frames": model.frames, "rays": model.rays, "steps": model.log.steps,
                   "seconds": round(model.log.seconds, 1), "train_psnr_db": round(model.log.psnr, 2),
                   "layers": bg_cfg.layers, "layer_px": bg_cfg.layer_px, "train_px": bg_cfg.train_size,
                   "object_sphere": {"center": sphere.center.round(6).tolist(), "radius": sphere.radius,
                                     "source": sphere.source},
                   "history": model.log.history})
    write_json(folder / "report.json", report)
    also = f" (and the room around the object in {len(video)} video frames)" if video else ""
    ctx.notes.append(f"background: {mode}, {model.frames} frames{also}, {model.log.steps} steps, "
                     f"training PSNR {model.log.psnr:.1f} dB")
    return BackgroundOutput(poses, sphere, model, report, windows, scale)


@dataclass(frozen=True)
class CropsOutput:
    """The crops stage's record: the crops dataset file and its records."""

    crops_json: Path
    records: tuple[CropRecord, ...]
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
            extra["sheet_frame"] = _sheet_frame(f.image, oc.cam, seg.intr, c2w, sp.center)
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
        _write_png(seg.out / f"crops/{fm.name}.png", cv2.cvtColor(oc.rgba, cv2.COLOR_RGBA2BGRA))
        if not oc.touches_border:       # past the border the observed crop is padding, not the room
            _write_png(seg.out / f"crops_observed/{fm.name}.png", cv2.cvtColor(oc.observed, cv2.COLOR_RGB2BGR))
            _write_png(seg.out / f"crops_background/{fm.name}.png", cv2.cvtColor(oc.predicted, cv2.COLOR_RGB2BGR))
        _write_png(seg.out / f"masks/{fm.name}.png",
                   alpha_in_frame(oc.rgba[..., 3], oc.cam, seg.frame_intr, seg.c2w[fm.index]))
        row = _sheet_tiles(sheet_frame, oc, prev) if sheet_frame is not None else None
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
    windows, scale = bg.windows, bg.scale
    if scale > 1:
        ctx.notes.append(f"crops matted at {scale}x ({scale * cfg.crop_size} px) and averaged down: the crop window "
                         f"spans {np.median(windows) / cfg.crop_size:.1f} source pixels per crop pixel (median)")

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
                                                cfg.crop_size, cfg.crop_fill, cfg.matte, scale, out / "background" / "field.pt",
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
    records = [CropRecord(f"crops/{p.name}.png", r.cam, p.index, p.time, str(sp), r.touches_border,
                          **({} if r.touches_border else {"observed_path": f"crops_observed/{p.name}.png",
                                                          "background_path": f"crops_background/{p.name}.png"}))
               for p, sp, r in zip(posed, splits, results)]
    coverage = [r.coverage for r in results]
    sheet_rows = [r.sheet_row for r in results if r.sheet_row is not None]
    doc = crops_json(records, sphere.center, sphere.radius, sphere.up, cfg.crop_size, cfg.crop_fill,
                     cfg.sequence_length)
    doc["note"] = "crop cameras: OpenGL camera-to-world, ChArUco board frame, metres; straight RGBA crops"
    write_json(out / "crops.json", doc)
    # The full frames get their masks (single channel, black = not the object).
    tf = read_json(out / "transforms.json", "transforms")
    for fr in tf["frames"]:
        fr["mask_path"] = "masks/" + Path(fr["file_path"]).stem + ".png"
    write_json(out / "transforms.json", tf)
    if sheet_rows:
        _write_png(out / "contact_sheet.png", cv2.cvtColor(np.concatenate(sheet_rows, 0), cv2.COLOR_RGB2BGR))
    touched = [r.file_path for r in records if r.touches_border]
    if touched:
        ctx.notes.append(f"{len(touched)} crops reach past the frame's border (padded transparent, flagged "
                         f"touches_border in crops.json): {', '.join(Path(t).stem for t in touched[:6])}"
                         f"{' ...' if len(touched) > 6 else ''}")
    stats = dataset_stats(doc, poses, bg, coverage)
    write_json(out / "dataset.json", stats)
    return CropsOutput(out / "crops.json", tuple(records), stats)


def _write_png(path: Path, img: np.ndarray) -> None:
    if not cv2.imwrite(str(path), img, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise DbbError(f"cannot write {path}")


def _sheet_row(frame: np.ndarray, intr: Intrinsics | None, c2w: np.ndarray | None, center: np.ndarray | None,
               oc: ObjectCrop, prev: np.ndarray | None, cell: int = 128,
               window: tuple[int, int, int] | None = None) -> np.ndarray:
    """frame (crop window drawn) | observed crop | predicted background | alpha | RGBA | dx, (cell, W, 3).

    The window is where the object centre projects (``intr``, ``c2w``, ``center``), or ``window``."""
    return _sheet_tiles(_sheet_frame(frame, oc.cam, intr, c2w, center, cell, window), oc, prev, cell)


def _sheet_frame(frame: np.ndarray, cam: Any, intr: Intrinsics | None, c2w: np.ndarray | None,
                 center: np.ndarray | None, cell: int = 128,
                 window: tuple[int, int, int] | None = None) -> np.ndarray:
    """The contact sheet's frame (cell high, RGB uint8) with the crop window drawn."""
    h, w = frame.shape[:2]
    scale = cell / h
    small = cv2.resize(frame, (max(1, round(w * scale)), cell), interpolation=cv2.INTER_AREA)
    if window is not None:
        uv = (np.array(window[:2], float) + window[2] / 2) * scale
    else:
        uv = project_points(center[None], c2w, intr)[0] * scale
    half = cam.window_px / 2 * scale
    x0, y0 = round(uv[0] - half), round(uv[1] - half)
    x1, y1 = round(uv[0] + half), round(uv[1] + half)
    cv2.rectangle(small, (x0, y0), (x1, y1), (255, 255, 0), 1)
    return small


def _sheet_tiles(small: np.ndarray, oc: ObjectCrop, prev: np.ndarray | None, cell: int = 128) -> np.ndarray:
    """A contact sheet row: the frame beside the crop's observed, predicted, alpha, RGBA and dx tiles."""
    tiles = [oc.observed, oc.predicted, np.repeat(oc.rgba[..., 3:], 3, -1), on_checker(oc.rgba),
             temporal_difference(prev, oc.rgba) if prev is not None else np.zeros_like(oc.observed)]
    tiles = [cv2.resize(t, (cell, cell), interpolation=cv2.INTER_NEAREST) for t in tiles]
    return np.concatenate([small] + tiles, 1)


def dataset_stats(doc: dict, poses: PosesOutput, bg: BackgroundOutput, coverage: list[float]) -> dict:
    """Summary statistics of the dataset (``dataset.json``)."""
    frames = doc["frames"]
    vp = np.array([[f["viewpoint"]["azimuth_deg"], f["viewpoint"]["elevation_deg"], f["viewpoint"]["distance_m"]]
                   for f in frames]) if frames else np.zeros((0, 3))

    def rng(col):
        return [round(float(vp[:, col].min()), 3), round(float(vp[:, col].max()), 3)] if len(vp) else None

    seqs = doc["sequences"]
    times = [f["time"] for f in frames]
    return {
        "frames_in_footage": poses.run.frames_in_footage, "frames_sampled": len(poses.run.frames),
        "frames_posed": len(poses.images), "crops": len(frames),
        "train": sum(f["split"] == "train" for f in frames), "test": sum(f["split"] == "test" for f in frames),
        "sequences": {"length": doc["sequence_length"], "train": sum(q["split"] == "train" for q in seqs),
                      "test": sum(q["split"] == "test" for q in seqs)},
        "duration_s": round(max(times) - min(times), 3) if times else 0.0,
        "crop_size": doc["crop_size"], "crop_fill": doc["crop_fill"],
        "touching_border": sum(bool(f["touches_border"]) for f in frames),
        "alpha_coverage_mean": round(float(np.mean(coverage)), 4) if coverage else 0.0,
        "viewpoint_range": {"azimuth_deg": rng(0), "elevation_deg": rng(1), "distance_m": rng(2)},
        "object": doc["object"], "up": doc["up"],
        "background": {k: bg.report[k] for k in ("mode", "frames", "video_room_frames", "steps", "train_psnr_db") if k in bg.report},
        "intrinsics_source": poses.run.intrinsics_source,
    }


# --------------------------------------------------------------------------- fixed camera
FIXED_HFOV_DEG = 60.0  # nominal field of view given to footage without a board (no metric camera)


def fixed_camera_stage(ctx: StageContext, _previous: Any = None) -> CropsOutput:
    """A fixed camera without a board: one crop window, a constant viewpoint.

    The background is the clean plate when there is one, else the per-pixel temporal median of
    the footage (for a camera that never moves, what most frames show at a pixel is the room:
    an object that rests in one place for most of the video is taken for the room, hence the
    option of opaque crops, ``fixed_matte=False``); each frame's window is matted against it. There is no metric pose: every crop shares one nominal camera (identity pose, a
    ``FIXED_HFOV_DEG`` field of view) and so one viewpoint; ``crops.json`` says so.
    """
    from ..crops.camera import CropCamera
    from ..geometry.viewpoint import viewpoint

    inp, cfg, out = ctx.inputs, ctx.cfg, ctx.out
    x, y, side = cfg.fixed_window
    info = inp.footage.info
    if side < 8 or x >= info.width or y >= info.height or x + side <= 0 or y + side <= 0:
        raise InputError(f"--crop-window {x},{y},{side} is outside the {info.width}x{info.height} frame")
    touches = x < 0 or y < 0 or x + side > info.width or y + side > info.height
    if touches:
        ctx.notes.append(f"the crop window {x},{y},{side} reaches past the frame's border: padded transparent, "
                         f"flagged touches_border")
    step = 1 if cfg.fps is None else max(1, round(info.fps / cfg.fps))
    indices = list(range(0, info.n_frames, step))
    with progress(transient=True) as prog:
        plate_src = open_footage(inp.background) if inp.background is not None else inp.footage
        if (plate_src.info.width, plate_src.info.height) != (info.width, info.height):
            raise InputError(f"the clean plate is {plate_src.info.width}x{plate_src.info.height} but the video is "
                             f"{info.width}x{info.height}")
        plate_idx = list(range(plate_src.info.n_frames))
        task = prog.add_task("background: temporal median", total=len(plate_idx), info="")
        picks = set(plate_idx[::max(1, len(plate_idx) // 150)])
        stack = []
        for f in plate_src.read(plate_idx):
            if f.index in picks:
                stack.append(_window(f.image, x, y, side))
            prog.advance(task)
        plate = np.median(np.stack(stack), axis=0).astype(np.uint8)
        bg_mode = ("temporal median of the clean plate" if inp.background is not None
                   else "temporal median of the video")
        (out / "background").mkdir()
        _write_png(out / "background" / "median_window.png", cv2.cvtColor(plate, cv2.COLOR_RGB2BGR))
        size = cfg.crop_size
        pred = cv2.resize(plate, (size, size), interpolation=cv2.INTER_AREA)
        inside = cv2.resize(_window(np.full((info.height, info.width, 3), 255, np.uint8), x, y, side), (size, size),
                            interpolation=cv2.INTER_AREA)[..., 0]
        f_src = info.width / 2 / np.tan(np.radians(FIXED_HFOV_DEG / 2))
        f_crop = f_src * size / side
        # The window's centre ray, and a camera at the origin looking down it (object 1 m away, nominal).
        ray = np.array([(x + side / 2 - 0.5 - (info.width - 1) / 2) / f_src,
                        (y + side / 2 - 0.5 - (info.height - 1) / 2) / f_src, 1.0])
        center = ray / np.linalg.norm(ray)
        up = np.array([0.0, -1.0, 0.0])
        c2w = np.eye(4)
        # The crop is a plain window of the nominal camera's frame: the same camera, its principal
        # point moved with the window (so the object centre projects to the crop's centre).
        s = size / side
        cx, cy = (info.width / 2 - x) * s - 0.5, (info.height / 2 - y) * s - 0.5
        cam = CropCamera(Intrinsics(size, size, f_crop, f_crop, cx, cy), c2w, viewpoint(np.zeros(3), center, up), side)
        radius = float(np.sin(np.arctan(side * cfg.crop_fill / 2 / f_src)))
        (out / "crops").mkdir()
        splits = split_by_time(np.array([info.times[i] for i in indices]), cfg.test_fraction)
        records, coverage, sheet, prev = [], [], [], None
        full = np.ones((size, size), bool)
        task = prog.add_task("matte and crop", total=len(indices), info="")
        sheet_at = set(np.linspace(0, len(indices) - 1, min(8, len(indices))).round().astype(int).tolist())
        for k, f in enumerate(inp.footage.read(indices)):
            obs = cv2.resize(_window(f.image, x, y, side), (size, size), interpolation=cv2.INTER_AREA)
            if cfg.fixed_matte:
                rgba = matte(obs, pred, full, cfg.matte)
                rgba[..., 3] = np.minimum(rgba[..., 3], inside)
            else:
                rgba = np.concatenate([obs, inside[..., None]], -1)
            rel = f"crops/{f.name}.png"
            _write_png(out / rel, cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
            records.append(CropRecord(rel, cam, f.index, f.time, str(splits[k]), touches))
            coverage.append(float(rgba[..., 3].mean()) / 255.0)
            if k in sheet_at:
                oc = ObjectCrop(cam, obs, pred, rgba, touches)
                sheet.append(_sheet_row(f.image, None, None, None, oc, prev, window=(x, y, side)))
            prev = rgba
            prog.advance(task)
    doc = crops_json(records, center, radius, up, size, cfg.crop_fill, cfg.sequence_length)
    doc["note"] = (f"fixed camera, no board: one nominal camera (identity pose, {FIXED_HFOV_DEG:g} deg field of "
                   f"view, object 1 m away along the window's centre ray) and one constant viewpoint; "
                   f"crop window {x},{y},{side} px; background: {bg_mode}"
                   + ("" if cfg.fixed_matte else "; not matted (opaque crops)"))
    doc["fixed_camera"] = {"window": [x, y, side], "hfov_deg": FIXED_HFOV_DEG}
    write_json(out / "crops.json", doc)
    if sheet:
        _write_png(out / "contact_sheet.png", cv2.cvtColor(np.concatenate(sheet, 0), cv2.COLOR_RGB2BGR))
    seqs = doc["sequences"]
    stats = {"mode": "fixed camera", "frames_in_footage": info.n_frames, "crops": len(records),
             "train": int(sum(r.split == "train" for r in records)), "test": int(sum(r.split == "test" for r in records)),
             "sequences": {"length": cfg.sequence_length, "train": sum(q["split"] == "train" for q in seqs),
                           "test": sum(q["split"] == "test" for q in seqs)},
             "duration_s": round(float(records[-1].time - records[0].time), 3) if records else 0.0,
             "crop_size": size, "crop_fill": cfg.crop_fill, "touching_border": len(records) if touches else 0,
             "alpha_coverage_mean": round(float(np.mean(coverage)), 4) if coverage else 0.0,
             "background": {"mode": bg_mode if cfg.fixed_matte else "none (opaque crops)", "frames": len(stack)}}
    write_json(out / "dataset.json", stats)
    write_json(out / "poses" / "report.json", {"mode": "fixed camera", "frames_in_footage": info.n_frames,
                                                "note": "no board: no poses; one nominal camera"})
    return CropsOutput(out / "crops.json", tuple(records), stats)


def _window(image: np.ndarray, x: int, y: int, side: int) -> np.ndarray:
    """The square window (side, side, C) of ``image`` at top-left (x, y); outside the frame is black."""
    h, w = image.shape[:2]
    out = np.zeros((side, side) + image.shape[2:], image.dtype)
    x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + side, w), min(y + side, h)
    if x1 > x0 and y1 > y0:
        out[y0 - y:y1 - y, x0 - x:x1 - x] = image[y0:y1, x0:x1]
    return out


STAGES: list[Stage] = [Stage("poses", poses_stage), Stage("background", background_stage),
                       Stage("crops", crops_stage)]
FIXED_STAGES: list[Stage] = [Stage("fixed camera", fixed_camera_stage)]



# --------------------------------------------------------------------------- orchestration
@dataclass(frozen=True)
class PreprocessResult:
    dataset: Path
    stages_run: tuple[str, ...]
    notes: tuple[str, ...]
    last: Any                        # the record of the last stage that ran


def stage_names() -> list[str]:
    return [s.name for s in STAGES]


def run_preprocess(inputs: CaptureInputs, out: Path, cfg: PreprocessConfig = PreprocessConfig(),
                   overwrite: bool = False) -> PreprocessResult:
    """Run the stages in order into ``out`` (written aside, renamed into place)."""
    cfg.validate()
    if cfg.stop_after is not None and cfg.stop_after not in stage_names():
        raise DbbError(f"--stop-after {cfg.stop_after}: unknown stage "
                       f"(expected one of {', '.join(stage_names())})")
    ran: list[str] = []
    stages = FIXED_STAGES if cfg.fixed_window is not None else STAGES
    if cfg.fixed_window is None and inputs.board is None:
        raise InputError(f"{inputs.root}: no board.json (or give --crop-window for a fixed camera without a board)")
    with atomic_dir(Path(out), overwrite=overwrite) as tmp:
        ctx = StageContext(inputs, cfg, tmp)
        record: Any = None
        for stage in stages:
            record = stage.run(ctx, record)
            ran.append(stage.name)
            if stage.name == cfg.stop_after:
                break
        write_json(tmp / "preprocess.json", {
            "capture": str(inputs.root.resolve()), "footage": str(inputs.footage.path.resolve()),
            "background": str(inputs.background.resolve()) if inputs.background else None,
            "stages_run": ran, "stop_after": cfg.stop_after, "fps": cfg.fps,
            "notes": ctx.notes})
    return PreprocessResult(Path(out), tuple(ran), tuple(ctx.notes), record)
