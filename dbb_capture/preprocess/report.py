"""What a dataset says of itself: ``dataset.json``'s statistics and the contact sheet (its rows,
and the sheet with its columns and frames named)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..core.images import with_header, with_row_labels
from ..crops.object import ObjectCrop, on_checker, temporal_difference
from ..datasets.records import Frame
from ..geometry.cameras import Intrinsics, project_points
from .background_stage import BackgroundOutput, ObjectSphere
from .inputs import PreprocessConfig
from .pose_stage import PosesOutput


def sheet_row(frame: np.ndarray, intr: Intrinsics | None, c2w: np.ndarray | None, center: np.ndarray | None,
               oc: ObjectCrop, prev: np.ndarray | None, cell: int = 128,
               window: tuple[int, int, int] | None = None) -> np.ndarray:
    """frame (crop window drawn) | observed crop | predicted background | alpha | RGBA | dx, (cell, W, 3).

    The window is where the object centre projects (``intr``, ``c2w``, ``center``), or ``window``."""
    return sheet_tiles(sheet_frame(frame, oc.cam, intr, c2w, center, cell, window), oc, prev, cell)


def sheet_frame(frame: np.ndarray, cam: Any, intr: Intrinsics | None, c2w: np.ndarray | None,
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


def sheet_tiles(small: np.ndarray, oc: ObjectCrop, prev: np.ndarray | None, cell: int = 128) -> np.ndarray:
    """A contact sheet row: the frame beside the crop's observed, predicted, alpha, RGBA and dx tiles."""
    tiles = [oc.observed, oc.predicted, np.repeat(oc.rgba[..., 3:], 3, -1), on_checker(oc.rgba),
             temporal_difference(prev, oc.rgba) if prev is not None else np.zeros_like(oc.observed)]
    tiles = [cv2.resize(t, (cell, cell), interpolation=cv2.INTER_NEAREST) for t in tiles]
    return np.concatenate([small] + tiles, 1)


SHEET_COLUMNS = ("frame and crop window", "observed crop", "predicted room", "alpha", "RGBA crop",
                 "change from previous")


def contact_sheet(rows: list[np.ndarray], names: list[str], cell: int = 128) -> np.ndarray:
    """The contact sheet (RGB uint8): :func:`sheet_tiles` rows under a band naming the columns,
    each row named by its frame."""
    sheet = np.concatenate(rows, 0)
    heights = [r.shape[0] for r in rows]
    sheet = with_row_labels(sheet, list(names), heights, width=90)
    frame_w = rows[0].shape[1] - (len(SHEET_COLUMNS) - 1) * cell
    return with_header(sheet, ["frame"] + list(SHEET_COLUMNS), [90, frame_w] + [cell] * (len(SHEET_COLUMNS) - 1))


def dataset_stats(frames: list[Frame], windows: list[tuple[int, str]], cfg: PreprocessConfig, sphere: ObjectSphere,
                  poses: PosesOutput, bg: BackgroundOutput, coverage: list[float]) -> dict:
    """Summary statistics of the dataset (``dataset.json``): crops ``frames``, sequence
    ``windows`` [(start, split)], each crop's alpha ``coverage`` (mean alpha, 0..1)."""
    vp = np.array([list(f.viewpoint.to_json().values()) for f in frames]) if frames else np.zeros((0, 3))

    def rng(col):
        return [round(float(vp[:, col].min()), 3), round(float(vp[:, col].max()), 3)] if len(vp) else None

    times = [round(f.time, 6) for f in frames]
    return {
        "frames_in_footage": poses.run.frames_in_footage, "frames_announced": poses.run.frames_announced,
        "frames_decoded": poses.run.frames_decoded, "frames_sampled": len(poses.run.frames),
        "frames_posed": len(poses.images), "crops": len(frames),
        "train": sum(f.split == "train" for f in frames), "test": sum(f.split == "test" for f in frames),
        "sequences": sequence_counts(windows, cfg.sequence_length),
        "duration_s": round(max(times) - min(times), 3) if times else 0.0,
        "crop_size": bg.geometry.crop_size, "crop_fill": cfg.crop_fill,
        "touching_border": sum(bool(f.touches_border) for f in frames),
        "alpha_coverage_mean": round(float(np.mean(coverage)), 4) if coverage else 0.0,
        "viewpoint_range": {"azimuth_deg": rng(0), "elevation_deg": rng(1), "distance_m": rng(2)},
        "object": {"center": [round(float(v), 6) for v in sphere.center], "radius": round(float(sphere.radius), 6)},
        "up": [float(v) for v in sphere.up],
        "background": {k: bg.report[k] for k in ("mode", "frames", "video_room_frames", "steps", "train_psnr_db") if k in bg.report},
        "intrinsics_source": poses.run.intrinsics_source,
    }


def sequence_counts(windows: list[tuple[int, str]], length: int) -> dict:
    return {"length": length, "train": sum(sp == "train" for _, sp in windows),
            "test": sum(sp == "test" for _, sp in windows)}
