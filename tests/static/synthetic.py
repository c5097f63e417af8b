"""Posed RGBA views of the synthetic toy with a room behind them, and the small field settings
the tests train with."""

from __future__ import annotations

import json

import numpy as np
import torch
from conftest import synthetic_object_frames

from dbb_capture.capture.board import BoardSpec
from dbb_capture.datasets.records import ObjectVolume, PosedDataset
from dbb_capture.datasets.transforms import intrinsics_fields, load_dataset
from dbb_capture.geometry.conventions import opengl_from_opencv
from dbb_capture.static.field import FieldConfig

TINY = FieldConfig(res_start=16, res_max=32, batch_rays=512, upsample_at=(0.3,), tv_points=2048)
BOARD = BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100")


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
         "transform_matrix": opengl_from_opencv(f.c2w).tolist(), "split": f.split, **intrinsics_fields(f.intr)}
        for f in frames]}
    (folder / "crops.json").write_text(json.dumps(doc))
    return load_dataset(folder), vol, truth
