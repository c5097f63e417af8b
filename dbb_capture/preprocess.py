"""``dbb-capture preprocess``: a capture folder -> a posed dataset, as a list of stages.

Each stage is a function ``(ctx, previous record) -> record`` writing its files into the
dataset folder being built, so a later stage can also start from those files alone. The
whole dataset is written aside and renamed into place at the end (``atomic_dir``).

Stages in this build: ``poses`` (footage -> undistorted frames, ``transforms.json``, COLMAP
model, pose report). Background removal and crops are planned after it; until they are
added to :data:`STAGES` a full run stops after ``poses`` and says so.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from .board import BoardSpec
from .cameras import Intrinsics
from .errors import DbbError, InputError
from .formats import PosedImage, Undistorter, plot_camera_path, pose_report, write_colmap, write_transforms
from .io import FootageSource, R3dSource, capture_footage, open_footage
from .outputs import atomic_dir, write_json
from .poses import DetectorConfig, PoseConfig, PoseRun, estimate_poses
from .progress import progress

PLANNED_STAGES = ("background", "crops")  # named in the docs; not part of this build yet


# --------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class CaptureInputs:
    """Where a capture's parts are. ``camera`` is None when intrinsics must be calibrated."""

    root: Path
    footage: FootageSource
    board: BoardSpec
    camera: Intrinsics | None
    camera_source: str
    object_json: Path | None
    background: Path | None


def resolve_capture(capture: Path, board: Path | None = None, camera: Path | None = None,
                    footage: Path | None = None, object_json: Path | None = None,
                    background: Path | None = None) -> CaptureInputs:
    """Find the parts of a capture folder (flags override the files inside it)."""
    capture = Path(capture)
    if not capture.is_dir():
        raise InputError(f"capture folder not found: {capture}")
    src = open_footage(footage) if footage else capture_footage(capture)
    src.info  # probe now: unreadable footage fails before any work starts
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


STAGES: list[Stage] = [Stage("poses", poses_stage)]


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
    if cfg.stop_after is not None and cfg.stop_after not in stage_names():
        if cfg.stop_after in PLANNED_STAGES:
            raise DbbError(f"--stop-after {cfg.stop_after}: that stage is not available in this "
                           f"build yet (available: {', '.join(stage_names())})")
        raise DbbError(f"--stop-after {cfg.stop_after}: unknown stage "
                       f"(expected one of {', '.join(stage_names())})")
    ran: list[str] = []
    with atomic_dir(Path(out), overwrite=overwrite) as tmp:
        ctx = StageContext(inputs, cfg, tmp)
        record: Any = None
        for stage in STAGES:
            record = stage.run(ctx, record)
            ran.append(stage.name)
            if stage.name == cfg.stop_after:
                break
        missing = [s for s in PLANNED_STAGES if s not in stage_names()]
        if cfg.stop_after is None and missing:
            ctx.notes.append(f"stopped after {ran[-1]}: the stages {', '.join(missing)} are not "
                             f"available in this build yet")
        write_json(tmp / "preprocess.json", {
            "capture": str(inputs.root.resolve()), "footage": str(inputs.footage.path.resolve()),
            "background": str(inputs.background.resolve()) if inputs.background else None,
            "stages_run": ran, "stop_after": cfg.stop_after, "fps": cfg.fps,
            "notes": ctx.notes})
    return PreprocessResult(Path(out), tuple(ran), tuple(ctx.notes), record)
