"""Posed RGBA views of the synthetic toy, and the small field settings the tests train with."""

from __future__ import annotations

import json
import math

import numpy as np
import torch

from dbb_capture.capture.board import BoardSpec
from dbb_capture.datasets.records import Frame, ObjectVolume, PosedDataset
from dbb_capture.datasets.transforms import load_dataset
from dbb_capture.geometry.cameras import Intrinsics
from dbb_capture.geometry.conventions import opengl_from_opencv
from dbb_capture.geometry.transforms import look_at
from dbb_capture.static.field import FieldConfig

TINY = FieldConfig(res_start=16, res_max=32, batch_rays=512, upsample_at=(0.3,), tv_points=2048)
BOARD = BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100")


def synthetic_object_frames(folder, n=24, size=32, seed=0) -> tuple[list[Frame], ObjectVolume]:
    """RGBA renders (size x size px, written to ``folder``) of the synthetic toy from known poses
    around it, every 8th (from the 4th) held out; and the sphere that holds it."""
    import cv2

    from dbb_capture.synth.objects import make_object
    from dbb_capture.synth.render import render_object_rgba

    model = make_object("static", BOARD, np.random.default_rng(seed))
    c, r = model.bounding_sphere(np.array([0.0]))
    f = size * 1.2
    intr = Intrinsics(size, size, f, f, (size - 1) / 2, (size - 1) / 2)
    dist = 1.1 * r / math.sin(math.atan(0.5 / 1.2))
    rng = np.random.default_rng(seed + 1)
    frames = []
    for i in range(n):
        az, el = 2 * math.pi * i / n + rng.uniform(0, 0.2), rng.uniform(0.15, 1.2)
        eye = c + dist * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), -math.sin(el)])
        c2w = look_at(eye, c, np.array([0, 0, -1.0]))
        p = folder / f"{i:03d}.png"
        cv2.imwrite(str(p), cv2.cvtColor(render_object_rgba(model, intr, c2w, 0.0, samples=2), cv2.COLOR_RGBA2BGRA))
        frames.append(Frame(f"{i:03d}", p, c2w, intr, "test" if i % 8 == 3 else "train"))
    return frames, ObjectVolume(tuple(float(v) for v in c), float(r) * 1.05)


def band2(cfg: FieldConfig) -> torch.Tensor:
    """(3 * n_basis,) bool: the SH table's degree-2 columns (each channel's coefficients 4..8)."""
    return (torch.arange(3 * cfg.n_basis) % cfg.n_basis) >= 4


def _room(size: int, rng: np.random.Generator) -> np.ndarray:
    """A smooth room behind one view (size, size, 3) uint8: two random colours blended across it."""
    c0, c1 = rng.uniform(20, 235, 3), rng.uniform(20, 235, 3)
    t = np.linspace(0, 1, size)[None, :, None] * np.ones((size, 1, 1))
    return np.round(c0 * (1 - t) + c1 * t).astype(np.uint8)


def crops_with_room(folder, holes: float = 0.33, seed: int = 3) -> tuple[PosedDataset, ObjectVolume, dict]:
    """A crops.json dataset of the synthetic toy whose mattes have holes (alpha 0 on ``holes``
    of the pixels), with each view's observed pixels and a smooth predicted room; and the
    true alpha per frame name."""
    import cv2

    frames, vol = synthetic_object_frames(folder, n=24, size=24)
    rng = np.random.default_rng(seed)
    truth = {}
    for f in frames:
        rgba = cv2.cvtColor(cv2.imread(str(f.image_path), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)
        truth[f.name] = rgba[..., 3].astype(np.float32) / 255
        room = _room(24, rng)
        a = rgba[..., 3:].astype(np.float32) / 255
        seen = np.round(rgba[..., :3] * a + room * (1 - a)).astype(np.uint8)
        bad = rgba.copy()
        bad[..., 3] = np.where(rng.random((24, 24)) < holes, 0, rgba[..., 3])
        cv2.imwrite(str(folder / f"{f.name}.png"), cv2.cvtColor(bad, cv2.COLOR_RGBA2BGRA))
        cv2.imwrite(str(folder / f"seen_{f.name}.png"), cv2.cvtColor(seen, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(folder / f"room_{f.name}.png"), cv2.cvtColor(room, cv2.COLOR_RGB2BGR))
    doc = {"camera_model": "OPENCV", "object": {"center": list(vol.center), "radius": vol.radius}, "frames": [
        {"file_path": f"{f.name}.png", "observed_path": f"seen_{f.name}.png", "background_path": f"room_{f.name}.png",
         "transform_matrix": opengl_from_opencv(f.c2w).tolist(), "split": f.split, **f.intr.nerfstudio_fields()}
        for f in frames]}
    (folder / "crops.json").write_text(json.dumps(doc))
    return load_dataset(folder), vol, truth
