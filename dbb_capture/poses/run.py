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
from ..capture.footage import FootageSource, blurry_mask, frames_decoded, sample_indices
from ..core.errors import DbbError
from ..geometry.cameras import Intrinsics
from .calibrate import ALL_DIST_TERMS, Calibration, IntrinsicsFit, calibrate_precise, intrinsics_fit
from .detect import Detection, DetectorConfig, detect_footage, detect_sampled
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
    frames_announced: int | None = None   # what the video's container announces (None: not a video)
    frames_decoded: int = 0        # of the footage's frames, those the decoder gave (estimated from the sampled ones)

    @property
    def posed(self) -> list[FramePose]:
        return [p for p in self.frames if p.posed]


PROBE_FRAMES = 24     # frames spread over the footage that given intrinsics are first checked on


def probe_views(source: FootageSource, board: BoardSpec, fps: float | None = None,
                det_cfg: DetectorConfig = DetectorConfig()) -> list[Detection]:
    """Board detections in :data:`PROBE_FRAMES` frames spread evenly over ``source`` (sampled to ``fps``)."""
    idx = sample_indices(source.info.times, fps)
    pick = np.unique(np.linspace(0, len(idx) - 1, min(PROBE_FRAMES, len(idx))).round().astype(int))
    return detect_footage(source, idx[pick], board, det_cfg)


def check_intrinsics(dets: list[Detection], board: BoardSpec, intr: Intrinsics, source: str,
                     hint: str) -> IntrinsicsFit | None:
    """The :class:`IntrinsicsFit` of ``intr`` (from ``source``) over board views ``dets``; a
    misfit is a :class:`DbbError` with both figures and ``hint``. None: too few views to judge."""
    fit = intrinsics_fit(dets, board, intr)
    if fit is not None and fit.misfit:
        raise DbbError(f"{source} does not fit this footage: board reprojection {fit.given_rms:.2g} px with "
                       f"its intrinsics, {fit.calibrated_rms:.2g} px calibrated from {fit.views} of the frames; "
                       f"{hint}")
    return fit


def estimate_poses(source: FootageSource, board: BoardSpec, intr: Intrinsics | None = None,
                   fps: float | None = None, blur_ratio: float = 0.4, refine: bool = False,
                   workers: int = 1, det_cfg: DetectorConfig = DetectorConfig(),
                   pose_cfg: PoseConfig = PoseConfig(), min_posed: int = 3,
                   tick: Callable[[int], None] | None = None, total: Callable[[int], None] | None = None,
                   intr_source: str = "camera.json", device_c2w: np.ndarray | None = None,
                   calib_views: int = 100, misfit_hint: str | None = None) -> PoseRun:
    """Frames of ``source`` -> metric camera poses in the board frame (see module doc).

    ``device_c2w`` (N, 4, 4): the device's own poses (Record3D), used where the board is hidden.
    Without ``intr``, the intrinsics are calibrated from at most ``calib_views`` diverse frames.
    With ``intr`` and a ``misfit_hint``, they are first checked against a handful of board views
    spread over the footage (:func:`check_intrinsics`). Raises :class:`DbbError` when no frame
    shows the board (naming the dictionary seen instead), when the given intrinsics misfit, or
    when fewer than ``min_posed`` frames can be posed.
    """
    info = source.info
    fit = None
    if intr is not None:
        if (intr.width, intr.height) != (info.width, info.height):
            raise DbbError(f"{intr_source} is for {intr.width}x{intr.height} images but the footage is "
                           f"{info.width}x{info.height}")
        if misfit_hint is not None:     # before the whole footage is searched for the board
            fit = check_intrinsics(probe_views(source, board, fps, det_cfg), board, intr, intr_source, misfit_hint)
    dets = detect_sampled(source, board, fps, det_cfg, workers, tick, total)
    decoded = frames_decoded(info, len(sample_indices(info.times, fps)), len(dets))
    blurry = blurry_mask(np.array([d.sharpness for d in dets]), blur_ratio)
    calib = None
    if intr is None:
        # Calibrating from the capture itself: every diverse view tightens the focal length.
        calib = calibrate_precise(source, [d for d, b in zip(dets, blurry) if not b], board, calib_views)
        intr, intr_source = calib.intrinsics, f"calibrated from the footage (RMS {calib.rms:.3f} px)"
    sharp = [d for d, b in zip(dets, blurry) if not b]
    if misfit_hint is not None and calib is None and fit is None:   # too few views in the probe: all of them
        check_intrinsics(sharp, board, intr, intr_source, misfit_hint)
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
    return PoseRun(intr, intr_source, frames, tuple(dets), calib, refined_rms, info.n_frames,
                   info.announced, decoded)
