"""A fixed camera without a board: one crop window and one constant viewpoint (``--crop-window``)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..capture.footage import open_footage
from ..core.errors import InputError
from ..core.images import write_image
from ..core.outputs import write_json
from ..core.progress import progress
from ..crops.matte import matte
from ..crops.object import ObjectCrop
from ..crops.sequences import sequence_windows, split_by_time
from ..datasets.records import Frame
from ..datasets.transforms import write_crops
from ..geometry.cameras import Intrinsics
from .crop_stage import CropsOutput
from .inputs import StageContext, note_crop_size
from .report import contact_sheet, sequence_counts, sheet_row

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
    x, y, side = cfg.crop_window
    info = inp.footage.info
    if side < 8 or x >= info.width or y >= info.height or x + side <= 0 or y + side <= 0:
        raise InputError(f"{{=crop_window}} {x},{y},{side} is outside the {info.width}x{info.height} frame")
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
        write_image(out / "background" / "median_window.png", cv2.cvtColor(plate, cv2.COLOR_RGB2BGR))
        # One viewpoint: a video for the RSSM, whatever object.json says.
        size, why = cfg.crop_size_for(np.array([float(side)]), "dynamic")
        note_crop_size(ctx, size, why)
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
        frames, coverage, sheet, sheet_names, prev = [], [], [], [], None
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
            write_image(out / rel, cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
            frames.append(Frame(f.name, out / rel, cam.c2w, cam.intr, str(splits[k]), time=f.time,
                                source_frame=f.index, viewpoint=cam.viewpoint, touches_border=touches))
            coverage.append(float(rgba[..., 3].mean()) / 255.0)
            if k in sheet_at:
                oc = ObjectCrop(cam, obs, pred, rgba, touches)
                sheet.append(sheet_row(f.image, None, None, None, oc, prev, window=(x, y, side)))
                sheet_names.append(f.name)
            prev = rgba
            prog.advance(task)
    windows = sequence_windows(np.array([f.time for f in frames]), splits, cfg.sequence_length)
    note = (f"fixed camera, no board: one nominal camera (identity pose, {FIXED_HFOV_DEG:g} deg field of "
            f"view, object 1 m away along the window's centre ray) and one constant viewpoint; "
            f"crop window {x},{y},{side} px; background: {bg_mode}"
            + ("" if cfg.fixed_matte else "; not matted (opaque crops)"))
    write_crops(out / "crops.json", frames, center, radius, up, size, cfg.crop_fill, cfg.sequence_length, windows,
                {"note": note, "fixed_camera": {"window": [x, y, side], "hfov_deg": FIXED_HFOV_DEG}})
    if sheet:
        write_image(out / "contact_sheet.png", cv2.cvtColor(contact_sheet(sheet, sheet_names), cv2.COLOR_RGB2BGR))
    stats = {"mode": "fixed camera", "frames_in_footage": info.n_frames, "crops": len(frames),
             "train": int(sum(f.split == "train" for f in frames)), "test": int(sum(f.split == "test" for f in frames)),
             "sequences": sequence_counts(windows, cfg.sequence_length),
             "duration_s": round(round(frames[-1].time, 6) - round(frames[0].time, 6), 3) if frames else 0.0,
             "crop_size": size, "crop_fill": cfg.crop_fill, "touching_border": len(frames) if touches else 0,
             "alpha_coverage_mean": round(float(np.mean(coverage)), 4) if coverage else 0.0,
             "background": {"mode": bg_mode if cfg.fixed_matte else "none (opaque crops)", "frames": len(stack)}}
    write_json(out / "dataset.json", stats)
    write_json(out / "poses" / "report.json", {"mode": "fixed camera", "frames_in_footage": info.n_frames,
                                                "note": "no board: no poses; one nominal camera"})
    return CropsOutput(out / "crops.json", tuple(frames), stats)


def _window(image: np.ndarray, x: int, y: int, side: int) -> np.ndarray:
    """The square window (side, side, C) of ``image`` at top-left (x, y); outside the frame is black."""
    h, w = image.shape[:2]
    out = np.zeros((side, side) + image.shape[2:], image.dtype)
    x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + side, w), min(y + side, h)
    if x1 > x0 and y1 > y0:
        out[y0 - y:y1 - y, x0 - x:x1 - x] = image[y0:y1, x0:x1]
    return out
