"""The background stage: the object's sphere, and a radiance field of the room from the clean plate
or from the object video with the object's sphere left out (:mod:`..background`)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from ..background.config import training_size
from ..background.model import BackgroundModel
from ..background.rays import TrainingView
from ..background.train import parallax_coverage, train_background
from ..capture.footage import FootageSource, open_footage
from ..capture.object_spec import load_object_sphere
from ..core.errors import InputError
from ..core.outputs import write_json
from ..core.progress import progress
from ..crops.camera import crop_windows
from ..crops.object import matte_scale
from ..datasets.records import estimate_volume
from ..geometry.cameras import Intrinsics, project_points
from ..geometry.viewpoint import up_from_cameras
from ..poses.export import plot_camera_path
from ..poses.run import estimate_poses
from .inputs import PreprocessConfig, StageContext, note_crop_size
from .pose_stage import PosesOutput


@dataclass(frozen=True)
class ObjectSphere:
    """The sphere that holds the object (board frame, metres) and the scene's up (3,)."""

    center: np.ndarray
    radius: float
    up: np.ndarray
    source: str                      # "object.json" or how it was estimated


@dataclass(frozen=True)
class MatteGeometry:
    """How the crops are cut: each posed frame's window, the crops' side and the matte's scale."""

    windows: np.ndarray          # (N,) crop window of each posed frame, source pixels
    crop_size: int               # pixels (:meth:`PreprocessConfig.crop_size_for`)
    why: str                     # where the crop size comes from, in words
    scale: int                   # matted at this many times the crop size (:func:`~.crops.matte_scale`)


@dataclass(frozen=True)
class BackgroundOutput:
    """The background stage's record: the trained room and what it was made from."""

    poses: PosesOutput
    sphere: ObjectSphere
    model: BackgroundModel
    report: dict
    geometry: MatteGeometry      # the crop windows, the crops' size and the matte's scale


def object_sphere(ctx: StageContext, poses: PosesOutput) -> ObjectSphere:
    """Read (or estimate, saying so) the object's sphere; check that the views see it."""
    c2ws = np.stack([im.c2w for im in poses.images])
    up = up_from_cameras(c2ws)
    if (ctx.out / "object.json").is_file():
        center, radius = load_object_sphere(ctx.out / "object.json")
        source = "object.json"
    else:
        vol = estimate_volume(list(poses.images))
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


def matte_geometry(cfg: PreprocessConfig, poses: PosesOutput, sphere: ObjectSphere,
                   kind: str | None = None) -> MatteGeometry:
    """The crop windows of the posed frames, the crop size for them and the object's ``kind``,
    and the scale the crops are matted at."""
    windows = crop_windows([p.c2w for p in poses.run.posed], poses.run.intrinsics, sphere.center, sphere.radius,
                           sphere.up, cfg.crop_fill)
    size, why = cfg.crop_size_for(windows, kind)
    return MatteGeometry(windows, size, why, matte_scale(windows, size, cfg.matte.supersample_between))


def _subsample(items: list, n: int) -> list:
    if len(items) <= n:
        return items
    return [items[i] for i in np.unique(np.linspace(0, len(items) - 1, n).round().astype(int))]


def _posed_views(src: FootageSource, intr: Intrinsics, posed: list) -> Iterator[TrainingView]:
    """The frames of ``posed`` (posed frame records) read from ``src`` as a stream of views."""
    by_index = {p.index: p for p in posed}
    if by_index:
        for f in src.read(sorted(by_index)):
            yield TrainingView(f.image, intr, by_index[f.index].c2w)


def background_stage(ctx: StageContext, poses: PosesOutput) -> BackgroundOutput:
    """Train the room's field; writes background/field.pt and background/report.json."""
    inp, cfg = ctx.inputs, ctx.cfg
    sphere = object_sphere(ctx, poses)
    if sphere.source != "object.json":               # the poses stage drew the path without it
        plot_camera_path(poses.run, inp.board, ctx.out / "poses" / "camera_path.png",
                         (sphere.center, sphere.radius), "object sphere (estimated)")
    intr = poses.run.intrinsics                      # of the footage as filmed (distortion included)
    plate = inp.background if cfg.use_clean_plate else None
    folder = ctx.out / "background"
    folder.mkdir()
    geo = matte_geometry(cfg, poses, sphere, inp.kind)
    note_crop_size(ctx, geo.crop_size, geo.why)
    bg_cfg = replace(cfg.background, train_size=training_size(cfg.background, geo.crop_size * geo.scale, cfg.crop_fill,
                                                              float(np.median(geo.windows)) if len(geo.windows) else 0.0))
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
    return BackgroundOutput(poses, sphere, model, report, geo)
