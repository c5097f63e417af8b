"""The pose stage end to end: footage -> detections -> intrinsics -> a :class:`PoseRun`.

Flow: frames -> :class:`~.detect.Detection` (board corners) -> intrinsics (given, or
:func:`~.calibrate.calibrate` from the detections) -> :class:`~.solve.FramePose` per frame -> outlier
rejection along the video -> optional joint refinement -> fusion with the camera path.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..capture.board import BoardSpec
from ..capture.footage import FootageSource, blurry_mask
from ..core.errors import DbbError
from ..geometry.cameras import Intrinsics
from .calibrate import ALL_DIST_TERMS, Calibration, calibrate_precise
from .detect import Detection, DetectorConfig, detect_sampled
from .path import fill_from_device, fuse_with_path, refine_jointly
from .solve import FramePose, PoseConfig, pose_frames, reject_outliers


@dataclass(frozen=True)
class PoseRun:
    """Everything the pose stage found: intrinsics (and where they came from), every sampled
    frame's pose or the reason it has none, and the blurred frames that were dropped."""

    intrinsics: Intrinsics
    intrinsics_source: str         # "camera.json", "calibrated (RMS 0.21 px)", "record3d"
    frames: tuple[FramePose, ...]
    detections: tuple[Detection, ...]
    calibration: Calibration | None = None
    refined_rms: float | None = None
    frames_in_footage: int = 0     # before sampling to --fps

    @property
    def posed(self) -> list[FramePose]:
        return [p for p in self.frames if p.posed]


def estimate_poses(source: FootageSource, board: BoardSpec, intr: Intrinsics | None = None,
                   fps: float | None = None, blur_ratio: float = 0.4, refine: bool = False,
                   workers: int = 1, det_cfg: DetectorConfig = DetectorConfig(),
                   pose_cfg: PoseConfig = PoseConfig(), min_posed: int = 3,
                   tick: Callable[[int], None] | None = None, total: Callable[[int], None] | None = None,
                   intr_source: str = "camera.json", device_c2w: np.ndarray | None = None,
                   calib_views: int = 100) -> PoseRun:
    """Frames of ``source`` -> metric camera poses in the board frame (see module doc).

    ``device_c2w`` (N, 4, 4): the device's own poses (Record3D), used where the board is hidden.
    Without ``intr``, the intrinsics are calibrated from at most ``calib_views`` diverse frames.
    Raises :class:`DbbError` when no frame shows the board (naming the dictionary seen
    instead) or fewer than ``min_posed`` frames can be posed.
    """
    info = source.info
    dets = detect_sampled(source, board, fps, det_cfg, workers, tick, total)
    blurry = blurry_mask(np.array([d.sharpness for d in dets]), blur_ratio)
    calib = None
    if intr is None:
        # Calibrating from the capture itself: every diverse view tightens the focal length.
        calib = calibrate_precise(source, [d for d, b in zip(dets, blurry) if not b], board, calib_views)
        intr, intr_source = calib.intrinsics, f"calibrated from the footage (RMS {calib.rms:.3f} px)"
    elif (intr.width, intr.height) != (info.width, info.height):
        raise DbbError(f"camera.json is for {intr.width}x{intr.height} but the footage is "
                       f"{info.width}x{info.height}")
    sharp = [d for d, b in zip(dets, blurry) if not b]
    poses = reject_outliers(pose_frames(sharp, board, intr, pose_cfg), pose_cfg)
    refined_rms = None
    if refine:
        intr, poses, refined_rms = refine_jointly(
            sharp, poses, board, intr, calib is not None and calib.square_pixels,
            calib.dist_terms if calib is not None else ALL_DIST_TERMS)
        poses = reject_outliers(poses, pose_cfg)
    poses = fuse_with_path(sharp, poses, board, intr, pose_cfg)
    if device_c2w is not None:
        poses = fill_from_device(poses, device_c2w)
    by_index = {p.index: p for p in poses}
    frames = tuple(by_index.get(d.index) or FramePose(d.index, d.time, d.name, "blurry",
                                                      n_corners=d.n_corners) for d in dets)
    n_posed = sum(p.status == "posed" for p in frames)
    if n_posed < min_posed:
        why = {}
        for p in frames:
            why[p.status] = why.get(p.status, 0) + 1
        raise DbbError(f"only {n_posed} of {len(frames)} frames could be posed (need {min_posed}): "
                       + ", ".join(f"{k}: {v}" for k, v in sorted(why.items())))
    return PoseRun(intr, intr_source, frames, tuple(dets), calib, refined_rms, info.n_frames)
