"""``dbb-capture preprocess``: a capture folder -> a posed dataset, as a list of stages.

Each stage is a function ``(ctx, previous record) -> record`` writing its files into the
dataset folder being built, so a later stage can also start from those files alone. The
whole dataset is written aside and renamed into place at the end (``atomic_dir``).

Stages: ``poses`` (footage -> undistorted frames, ``transforms.json``, COLMAP model, pose
report), ``background`` (a radiance field of the room, from the clean plate or from the object
video with the object's sphere left out; :mod:`..background`), ``crops`` (per frame: crop
camera, predicted background, matte, straight RGBA crop; ``crops.json``, full-frame masks,
``dataset.json`` statistics and a contact sheet).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..core.errors import DbbError, InputError
from ..core.outputs import atomic_dir, write_json
from .background_stage import background_stage
from .crop_stage import crops_stage
from .fixed_camera import fixed_camera_stage
from .inputs import CaptureInputs, PreprocessConfig, Stage, StageContext
from .pose_stage import poses_stage

STAGES: list[Stage] = [Stage("poses", poses_stage), Stage("background", background_stage),
                       Stage("crops", crops_stage)]


FIXED_STAGES: list[Stage] = [Stage("fixed camera", fixed_camera_stage)]


@dataclass(frozen=True)
class PreprocessResult:
    dataset: Path
    stages_run: tuple[str, ...]
    notes: tuple[str, ...]
    warnings: tuple[str, ...]
    last: Any                        # the record of the last stage that ran


def stage_names() -> list[str]:
    return [s.name for s in STAGES]


def run_preprocess(inputs: CaptureInputs, out: Path, cfg: PreprocessConfig = PreprocessConfig(),
                   overwrite: bool = False) -> PreprocessResult:
    """Run the stages in order into ``out`` (written aside, renamed into place)."""
    cfg.validate()
    if cfg.stop_after is not None and cfg.stop_after not in stage_names():
        raise DbbError(f"{{=stop_after}} {cfg.stop_after}: unknown stage "
                       f"(expected one of {', '.join(stage_names())})")
    ran: list[str] = []
    stages = FIXED_STAGES if cfg.crop_window is not None else STAGES
    if cfg.crop_window is None and inputs.board is None:
        raise InputError(f"{inputs.root}: no board.json (or give {{=crop_window}} for a fixed camera without a board)")
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
            "notes": ctx.notes, "warnings": ctx.warnings})
    return PreprocessResult(Path(out), tuple(ran), tuple(ctx.notes), tuple(ctx.warnings), record)
