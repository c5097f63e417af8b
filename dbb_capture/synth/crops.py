"""Synthetic crop datasets: a crops.json dataset rendered straight from a synthetic dynamic object,
with the truth of its motion at a still viewpoint (for the RSSM's tests and benchmarks)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..core.progress import progress
from ..crops.camera import crop_camera
from ..crops.sequences import sequence_windows, split_by_time
from ..datasets.records import Frame
from ..datasets.transforms import write_crops
from .objects import UP
from .path import camera_path
from .render import render_object_rgba
from .scene import SynthConfig, make_scene

SEQUENCE_LENGTH = 11     # preprocess's default windows: 1 context + 10 predicted frames


@dataclass(frozen=True)
class SyntheticCrops:
    """A crops.json dataset rendered straight from a synthetic dynamic object (no preprocess)."""

    root: Path
    still_first: np.ndarray         # (S, S, 4) uint8: first frame of the still-viewpoint truth
    still_view: np.ndarray          # (3,) its viewpoint [azimuth_deg, elevation_deg, distance_m]
    still_truth: np.ndarray         # (steps, S, S, 4) uint8: the following frames, same viewpoint


def synthetic_crops(out: Path, seconds: float = 60.0, fps: float = 10.0, size: int = 64, seed: int = 0,
                    still_steps: int = 150, samples: int = 2) -> SyntheticCrops:
    """Render a dynamic toy along a handheld camera path into ``out/crops/`` + ``out/crops.json``.

    Exactly what the preprocess crop stage writes, with perfect mattes; the last 20 % of the
    time is the test split. Also renders ``still_steps`` frames after the first test frame
    at that frame's (now still) viewpoint: the truth of the motion-energy ratio.
    """
    cfg = SynthConfig(kind="dynamic", seconds=seconds, fps=fps, seed=seed, background_seconds=None)
    rng = np.random.default_rng(seed)
    scene = make_scene(cfg, rng)
    times = np.arange(round(seconds * fps)) / fps
    poses = camera_path(cfg, scene, times, rng)
    intr = cfg.intrinsics()
    center, radius = scene.obj.bounding_sphere(times[:: max(1, len(times) // 200)])
    radius *= 1.05
    splits = split_by_time(times)
    out = Path(out)
    (out / "crops").mkdir(parents=True, exist_ok=True)
    frames = []
    cams = []
    with progress(transient=True) as prog:
        task = prog.add_task("render crops", total=len(times), info="")
        for i, (t, c2w) in enumerate(zip(times, poses)):
            cam = crop_camera(c2w, intr, center, radius, UP, size, 0.9)
            rgba = render_object_rgba(scene.obj, cam.intr, cam.c2w, float(t), samples)
            cv2.imwrite(str(out / "crops" / f"{i:05d}.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
            frames.append(Frame(f"{i:05d}", out / "crops" / f"{i:05d}.png", cam.c2w, cam.intr, str(splits[i]),
                                time=float(t), source_frame=i, viewpoint=cam.viewpoint, touches_border=False))
            cams.append(cam)
            prog.update(task, advance=1)
        write_crops(out / "crops.json", frames, center, radius, UP, size, 0.9, SEQUENCE_LENGTH,
                    sequence_windows(times, splits, SEQUENCE_LENGTH))
        k = int(np.flatnonzero(splits == "test")[0]) if (splits == "test").any() else 0
        cam = cams[k]
        still = []
        task = prog.add_task("render still truth", total=still_steps + 1, info="")
        for j in range(still_steps + 1):
            still.append(render_object_rgba(scene.obj, cam.intr, cam.c2w, float(times[k] + j / fps), samples))
            prog.update(task, advance=1)
    v = cam.viewpoint
    return SyntheticCrops(out, still[0], np.array([v.azimuth_deg, v.elevation_deg, v.distance_m], np.float32),
                          np.stack(still[1:]))
