"""The poses stage: footage -> undistorted frames, ``transforms.json``, ``camera.json``, a COLMAP
model and the pose report (:mod:`..poses`)."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..capture.footage import R3dSource
from ..core.images import write_image
from ..core.outputs import write_json
from ..core.progress import progress
from ..datasets.records import Frame
from ..datasets.transforms import write_transforms
from ..geometry.cameras import Intrinsics
from ..geometry.undistort import Undistorter
from ..poses.export import (
    Sighting,
    board_points,
    corner_pixels,
    plot_camera_path,
    pose_report,
    sample_colours,
    write_colmap,
    write_ply,
)
from ..poses.run import PoseRun, estimate_poses
from .inputs import R3D_INTRINSICS, CaptureInputs, StageContext


@dataclass(frozen=True)
class PosesOutput:
    """The poses stage's record: the dataset's (undistorted) camera and its posed images."""

    transforms: Path
    intrinsics: Intrinsics           # of the undistorted frames
    images: tuple[Frame, ...]        # the undistorted frames (images/) and their poses
    up: tuple[float, float, float]   # the board normal on the cameras' side
    run: PoseRun


POINT_CLOUD = "sparse_pc.ply"     # the board's corners (nerfstudio's name for a dataset's point cloud)


def poses_stage(ctx: StageContext, _previous: Any = None) -> PosesOutput:
    """Footage -> poses; writes images/, transforms.json, camera.json, colmap/sparse/0, poses/."""
    inp, cfg, out = ctx.inputs, ctx.cfg, ctx.out
    with progress(transient=True) as prog:
        task = prog.add_task("detect board", total=None, info="")
        run = estimate_poses(
            inp.footage, inp.board, inp.camera, fps=cfg.fps, blur_ratio=cfg.blur_ratio,
            refine=cfg.refine, workers=cfg.workers, det_cfg=cfg.detector, pose_cfg=cfg.gates,
            tick=lambda n: prog.advance(task, n), total=lambda n: prog.update(task, total=n),
            intr_source=inp.camera_source, misfit_hint=_misfit_hint(inp),
            device_c2w=inp.footage.arkit_c2w_opencv() if isinstance(inp.footage, R3dSource) else None)
        check_decoded(ctx, run)
        posed = run.posed
        undistort = Undistorter(run.intrinsics)
        intr = undistort.target
        (out / "images").mkdir()
        task = prog.add_task("write undistorted frames", total=len(posed), info="")
        images, sightings = [], []
        by_index = {p.index: p for p in posed}
        corners = corner_pixels(run, run.intrinsics)
        for f in inp.footage.read(sorted(by_index)):
            p = by_index[f.index]
            img = undistort(f.image)
            write_image(out / "images" / f"{f.name}.png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            images.append(Frame(f.name, out / "images" / f"{f.name}.png", p.c2w, intr, time=p.time))
            ids, xy = corners.get(f.index, (None, None))
            sightings.append(None if ids is None else Sighting(ids, xy, sample_colours(img, xy)))
            prog.advance(task)
    points = board_points(inp.board, sightings)
    write_ply(out / POINT_CLOUD, points)
    # "Up" is the board normal on the cameras' side, read from the poses, never assumed.
    side = np.sign(np.median([im.c2w[2, 3] for im in images])) or -1.0
    up = (0.0, 0.0, float(side))
    write_frames(out / "transforms.json", images, up)
    cam = run.intrinsics.to_json()
    if run.calibration is not None:
        cam["rms"] = round(run.calibration.rms, 4)
    write_json(out / "camera.json", cam)
    write_colmap(out / "colmap" / "sparse" / "0", intr, images, out / "images", points)
    write_json(out / "poses" / "report.json", pose_report(run, inp.board))
    write_json(out / "board.json", inp.board.to_json())
    plot_camera_path(run, inp.board, out / "poses" / "camera_path.png", _sphere_of(inp.object_json))
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
    return PosesOutput(out / "transforms.json", intr, tuple(images), up, run)


def check_decoded(ctx: StageContext, run: PoseRun) -> None:
    """A video that decodes to fewer frames than its container announces (a copy cut short, a
    damaged stream; too few of them are refused while posing,
    :func:`~..capture.footage.frames_decoded`): a warning, kept in the dataset's record."""
    announced, got = run.frames_announced, run.frames_decoded
    if announced and got < announced:
        ctx.warnings.append(f"video {ctx.inputs.footage.path.name}: {got} of the {announced} frames its container "
                            f"announces could be decoded (the file is cut short or damaged); going on with those")


def _sphere_of(object_json: Path | None) -> tuple[np.ndarray, float] | None:
    """The sphere of an ``object.json`` for the camera-path plot, None where there is none yet
    (the background stage checks the file and draws an estimated sphere)."""
    try:
        d = json.loads(Path(object_json).read_text()) if object_json is not None else None
        c, r = np.asarray(d["center"], float).reshape(3), float(d["radius"])
    except (OSError, TypeError, KeyError, ValueError):
        return None
    return (c, r) if np.all(np.isfinite(c)) and np.isfinite(r) and r > 0 else None


def _misfit_hint(inp: CaptureInputs) -> str | None:
    """What to do when the given intrinsics misfit the footage (None: calibrated here, no check)."""
    if inp.camera is None:
        return None
    if inp.camera_source == R3D_INTRINSICS:
        return "calibrate the camera (dbb-capture calibrate) and pass --camera"
    return "recalibrate or omit camera.json"


def write_frames(path: Path, frames: list[Frame], up: tuple[float, float, float]) -> None:
    """The full frames' ``transforms.json``: the shared undistorted camera, the scene's up and the
    board's corners as the point cloud (``ply_file_path``, written beside it by the poses stage)."""
    write_transforms(path, frames, extra={"up": list(up), "ply_file_path": POINT_CLOUD,
                                          "note": "OpenGL camera-to-world, ChArUco board frame, metres; frames undistorted"})
